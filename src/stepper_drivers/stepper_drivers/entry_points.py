"""Executables: one function per vendor node. Vendor modules are imported only when used."""

from __future__ import annotations

import importlib
import sys

VENDOR_MODULES = {
    'xmind_k_node': 'stepper_drivers.vendors.xmind_k',
    'xplus_mt_node': 'stepper_drivers.vendors.xplus_mt',
    'rd4_node': 'stepper_drivers.vendors.rd4',
    'vector_step_node': 'stepper_drivers.vendors.vector_step',
}


def run(exe: str, argv: list[str] | None = None) -> int:
    import rclpy

    from .node import DriveNode, spin_node
    from .params import ParameterError, declare_all, non_ros_args

    vendor = importlib.import_module(VENDOR_MODULES[exe]).VENDOR
    argv = sys.argv if argv is None else argv
    try:
        extra = non_ros_args(argv)[1:]      # a missing or broken params file fails here
    except ParameterError as e:
        print(f'{exe}: {e}', file=sys.stderr, flush=True)
        return 2
    if extra:
        print(f'{exe}: unexpected arguments {extra}; usage: {exe} --ros-args --params-file '
              'FILE.yaml', file=sys.stderr)
        return 2
    rclpy.init(args=argv)
    try:
        node = DriveNode(vendor, exe, lambda n: declare_all(n, vendor))
    except ParameterError as e:
        print(f'{exe}: {e}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    spin_node(node)
    return 0


def xplus_mt_node() -> None:
    sys.exit(run('xplus_mt_node'))


def xmind_k_node() -> None:
    sys.exit(run('xmind_k_node'))


def rd4_node() -> None:
    sys.exit(run('rd4_node'))


def vector_step_node() -> None:
    sys.exit(run('vector_step_node'))


def socketcand_broker() -> None:
    from .protocol.socketcand_broker import main
    sys.exit(main())


def stepperctl() -> None:
    from .cli.main import main
    sys.exit(main())
