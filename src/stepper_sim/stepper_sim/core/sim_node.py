"""The ROS wrapper every simulator executable uses: `run_sim(node_name, build)`.

A simulator module implements `SimBackend` (no rclpy needed there) and its `main()` is

    def main(args=None):
        sys.exit(run_sim('xplus_mt_sim', build))

where `build(node)` declares the simulator's own parameters on the node (helpers `declare()` and
`declare_drives()` below), constructs the backend and returns it. `run_sim` then
  1. starts the backend's wire server (`backend.start()` returns, once it listens, its address),
  2. publishes each drive's true position on `~/<drive>/true_position_steps` (std_msgs/Float64,
     `publish_rate_hz`, default 20 Hz): the simulated drive's exact position counter in steps,
  3. offers `~/inject_fault` (stepper_drivers_msgs/srv/InjectFault) and `~/set_input`
     (stepper_drivers_msgs/srv/SetInput), which call the backend,
  4. prints `<node_name>: ready on <address>` on stdout (flushed; tests wait for this line),
  5. spins until SIGINT/SIGTERM, stops the backend, and returns exit code 0.
A bad parameter (ValueError from `build`, or rclpy's range checks) or a params file that cannot be
read or parsed prints one line naming it on stderr and returns 2, as the driver nodes do; a wire
server that cannot start (OSError: port in use) returns 1. Simulators bind to 127.0.0.1 only.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, Callable, Mapping, Protocol, Sequence, runtime_checkable

from rcl_interfaces.msg import ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64
from stepper_drivers.ros.params import ParameterError, non_ros_args
from stepper_drivers_msgs.srv import InjectFault, SetInput

logger = logging.getLogger(__name__)


@runtime_checkable
class SimBackend(Protocol):
    """A simulated bus with one or more drives, independent of ROS (structural type: a backend
    needs no import of this module, so its device model stays free of rclpy)."""

    def start(self) -> str:
        """Start the wire server; return once it listens, with its address ('127.0.0.1:1502')."""

    def stop(self) -> None:
        """Stop the server and every thread/task it started (idempotent)."""

    @property
    def drive_names(self) -> Sequence[str]: ...

    def true_position_steps(self, drive: str) -> float: ...

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        """Inject a link or drive fault; (success, message). Unknown kinds list the known ones."""

    def set_input(self, drive: str, name: str, value: bool,
                  release: bool) -> tuple[bool, str]: ...


def declare(node: Node, name: str, default: Any, description: str, *,
            read_only: bool = True) -> Any:
    """Declare one parameter and return its value; floats also accept YAML integers."""
    is_float = isinstance(default, float)
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     dynamic_typing=is_float)
    if isinstance(default, list) and not default:
        value = node.declare_parameter(name, Parameter.Type.STRING_ARRAY, descriptor).value
        return list(value) if value is not None else []
    value = node.declare_parameter(name, default, descriptor).value
    if value is None:           # rcl leaves an empty YAML list ([]) NOT_SET
        if isinstance(default, list):
            return []
        raise ValueError(f'parameter {name}: [] is not allowed (default: {default!r})')
    if is_float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'parameter {name}: expected a number, got {value!r}')
        return float(value)
    if isinstance(value, (list, tuple)):
        return list(value)
    return value


def declare_drives(node: Node, default_names: Sequence[str],
                   per_drive: Mapping[str, tuple[Any, str]]) -> dict[str, dict[str, Any]]:
    """Declare `drives` (string list) and `drives.<name>.<param>` for each; return the values."""
    names = declare(node, 'drives', list(default_names), 'names of the simulated drives')
    if not names:
        raise ValueError('parameter drives: at least one drive name is needed')
    if len(set(names)) != len(names):
        raise ValueError(f'parameter drives: names must be unique, got {names}')
    result: dict[str, dict[str, Any]] = {}
    for drive in names:
        result[drive] = {key: declare(node, f'drives.{drive}.{key}', default, description)
                         for key, (default, description) in per_drive.items()}
    return result


class _SimNode:
    """Publishers and services of one simulator node around its backend."""

    def __init__(self, node: Node, backend: SimBackend, publish_rate_hz: float):
        self.node = node
        self.backend = backend
        self._publishers = {
            drive: node.create_publisher(Float64, f'~/{drive}/true_position_steps', 10)
            for drive in backend.drive_names}
        self._timer = node.create_timer(1.0 / publish_rate_hz, self._publish)
        node.create_service(InjectFault, '~/inject_fault', self._inject_fault)
        node.create_service(SetInput, '~/set_input', self._set_input)

    def _publish(self) -> None:
        for drive, publisher in self._publishers.items():
            try:
                publisher.publish(Float64(data=float(self.backend.true_position_steps(drive))))
            except Exception:
                logger.exception('true position of %s', drive)

    def _inject_fault(self, request, response):
        response.success, response.message = self._call(
            self.backend.inject_fault, request.drive, request.kind, request.code, request.value)
        self.node.get_logger().info(
            f'inject_fault {request.drive} {request.kind} code=0x{request.code & 0xFFFF:04X} '
            f'value={request.value}: {response.message}')
        return response

    def _set_input(self, request, response):
        response.success, response.message = self._call(
            self.backend.set_input, request.drive, request.input, request.value, request.release)
        self.node.get_logger().info(f'set_input {request.drive} {request.input}: '
                                    f'{response.message}')
        return response

    @staticmethod
    def _call(fn, *args) -> tuple[bool, str]:
        try:
            ok, message = fn(*args)
            return bool(ok), str(message)
        except Exception as exc:   # a service must answer; the message names the problem
            logger.exception('simulator service failed')
            return False, f'{type(exc).__name__}: {exc}'


def run_sim(node_name: str, build: Callable[[Node], SimBackend],
            args: Sequence[str] | None = None) -> int:
    """Run one simulator node until SIGINT/SIGTERM; return the process exit code."""
    logging.basicConfig(level=logging.INFO, format=f'[{node_name}] %(levelname)s %(name)s: '
                                                   '%(message)s')
    try:
        non_ros_args(sys.argv if args is None else args)  # a missing or broken params file
    except ParameterError as exc:
        print(f'{node_name}: {exc}', file=sys.stderr, flush=True)
        return 2
    rclpy.init(args=args)
    node: Node | None = None
    backend: SimBackend | None = None
    rc = 0
    try:
        node = Node(node_name)
        rate = declare(node, 'publish_rate_hz', 20.0, 'rate of ~/<drive>/true_position_steps')
        if not 0.1 <= rate <= 1000.0:
            raise ValueError(f'parameter publish_rate_hz: {rate} not in 0.1..1000')
        backend = build(node)
        address = backend.start()
        _SimNode(node, backend, rate)
        print(f'{node_name}: ready on {address}', flush=True)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as exc:
        print(f'{node_name}: {exc}', file=sys.stderr, flush=True)
        rc = 2
    except OSError as exc:
        print(f'{node_name}: {exc}', file=sys.stderr, flush=True)
        rc = 1
    finally:
        if backend is not None:
            backend.stop()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return rc
