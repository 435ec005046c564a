"""Test harness: the project's own process and ROS client helpers (stepper_sim.harness,
stepper_drivers.cli.ros_client), and `DriveBench`: a vendor's simulator and node processes, as
every end-to-end test uses them.

ROS message packages are imported where used, so this module imports without them.
"""

import os
import signal
import subprocess
import threading
import time

# re-exported (hence F401): the test modules import the harness' pieces from here
from stepper_drivers.cli.ros_client import RosClient  # noqa: F401
from stepper_sim.harness import CONFIG, INSTALL, ROOT, Proc, executable, free_port, wait_for  # noqa: F401

# How long the processes still running at a test's end get to end on SIGINT before SIGKILL.
END_GRACE_S = 3.0


class Procs(list):
    """Processes started for a test or a module, logs in log_dir; kill_all() ends them by PID.
    It asks first (SIGINT to every one still running, then at most END_GRACE_S for them all):
    a ROS process that ends so removes its Fast DDS shared-memory files from /dev/shm, a killed
    one leaves them, and thousands of them stall the start of every ROS process on the machine
    (docs/troubleshooting.md)."""

    def __init__(self, log_dir):
        super().__init__()
        self.log_dir = log_dir

    def start(self, name, args, env=None) -> Proc:
        p = Proc(args, self.log_dir, name, env)
        self.append(p)
        return p

    def kill_all(self) -> None:
        # (a rig may put an object of its own here that only has kill(): rigs_vendors._Closer)
        running = [p for p in reversed(self)
                   if isinstance(p, Proc) and p.proc.poll() is None]
        for p in running:
            try:
                os.killpg(p.proc.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + END_GRACE_S
        for p in running:
            try:
                p.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for p in running:
            # the whole group, whether its leader has ended or not: a child that outlives its
            # leader after the SIGINT must not outlive the test
            try:
                os.killpg(p.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for p in reversed(self):
            p.kill()                   # reaps and closes the logs


class DriveBench:
    """A vendor's simulator and node as separate processes, and the ROS calls tests make on them.

    A subclass names the vendor (executables `<vendor>_sim` and `<vendor>_node`, parameter files
    config/<vendor>_sim.yaml and config/<vendor>.yaml), its drives and what connects node and
    simulator (`link_args()`: a pty path, a TCP port, a CAN broker's port). The node reconnects
    every 0.2 s; every drive is connected when the constructor returns.
    """

    vendor = ''
    drives = ('axis1', 'axis2')
    node_extra_args: tuple[str, ...] = ()     # node parameters after the link's
    first_sim_args: tuple[str, ...] = ()      # simulator parameters of the first start only
    keep_status = False                       # keep every DriveStatus in ros.history
    connect_timeout_s = 30.0                  # process starts take seconds on a busy machine
    wait_connected = True                     # the constructor returns once all are connected
    node_executable = ''                      # '' = <vendor>_node (the lifecycle one: ...)
    node_env: dict[str, str] = {}             # the node process's further environment
    # The bus owners on the normal scheduler: here the simulators, the CAN broker and pytest
    # share two cores with the nodes, and owners on SCHED_FIFO (the default, 10) would take the
    # CPU from the drives they talk to, which real drives do not need. The test of the default
    # sets this to ().
    owner_priority_args: tuple[str, ...] = ('-p', 'owner_thread_priority:=0')

    def __init__(self, procs, ros, node_args=()):
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64
        from stepper_drivers_msgs.msg import DriveStatus
        self.procs, self.ros = procs, ros
        self.node_ns, self.sim_ns = f'/{self.vendor}_node', f'/{self.vendor}_sim'
        self.sim = None
        self.start_sim(*self.first_sim_args)
        self.node = procs.start('node', [
            executable('stepper_drivers', self.node_executable or f'{self.vendor}_node'),
            '--ros-args',
            '--params-file', str(CONFIG / f'{self.vendor}.yaml'), *self.link_args(),
            '-p', 'reconnect_period_s:=0.2', *self.owner_priority_args,
            *self.node_extra_args, *node_args],
            env=self.node_env)
        ros.subscribe(JointState, '/joint_states', keep=True)
        ros.subscribe(DiagnosticArray, '/diagnostics')
        for d in self.drives:
            ros.subscribe(DriveStatus, f'{self.node_ns}/{d}/status', keep=self.keep_status)
            ros.subscribe(Float64, self.true_topic(d))
        if self.wait_connected:
            for d in self.drives:
                self.status(d, lambda m: m.connected, self.connect_timeout_s, f'{d} connected')

    # ------------------------------------------------------------------ vendor specific
    def link_args(self) -> list[str]:
        """The parameters (for both processes) that put node and simulator on one link."""
        raise NotImplementedError

    def sim_args(self) -> list[str]:
        """Further simulator parameters (storage folder, line timing)."""
        return []

    # ------------------------------------------------------------------------ processes
    def start_sim(self, *extra_args):
        """(Re)start the simulator and wait for its ready line; a restart forgets what the
        previous simulator published."""
        for d in self.drives:
            with self.ros.lock:
                self.ros.latest.pop(self.true_topic(d), None)
        name = 'sim' if self.sim is None else f'sim{len(self.procs) + 1}'
        self.sim = self.procs.start(name, [
            executable('stepper_sim', f'{self.vendor}_sim'), '--ros-args',
            '--params-file', str(CONFIG / f'{self.vendor}_sim.yaml'), *self.link_args(),
            *self.sim_args(), *extra_args])
        self.sim.wait_line('ready', 30.0)

    def sigterm_while_running(self, velocity, drives=('axis1',)):
        """Enable the drives, run them at `velocity` [rad/s], then SIGTERM the node: it must
        end with exit code 0."""
        for d in drives:
            self.enable(d)
            self.command(d, 'velocity_command', velocity)
        for d in drives:
            self.status(d, lambda m: m.moving, what=f'{d} running')
        assert self.node.stop(signal.SIGTERM) == 0

    def home_under_way(self, drive='axis1'):
        """Enable `drive`, call its `home` (it answers when the homing ends) and return once
        the axis moves: (the call's future, an event set when it answered)."""
        from std_srvs.srv import Trigger
        self.enable(drive)
        client = self.ros.node.create_client(Trigger, f'{self.node_ns}/{drive}/home')
        assert client.wait_for_service(timeout_sec=10)
        answered = threading.Event()
        fut = client.call_async(Trigger.Request())
        fut.add_done_callback(lambda _f: answered.set())
        self.status(drive, lambda m: m.moving, what='homing under way')
        assert not answered.is_set()
        return fut, answered

    def stop_during_homing(self, drive, bound_s):
        """`home`, then `stop` while it runs: the call must end with 'homing interrupted'
        within bound_s of the stop (not at homing.timeout_s)."""
        fut, answered = self.home_under_way(drive)
        r = self.call(drive, 'stop')
        assert r.success, r.message
        t_stop = time.monotonic()
        assert answered.wait(bound_s + 2.0), 'home still waiting 2 s past the bound'
        took = time.monotonic() - t_stop
        r = fut.result()
        assert not r.success and 'homing interrupted' in r.message, r.message
        assert took <= bound_s, (took, bound_s)

    # ------------------------------------------------------------------------------ ROS
    def status(self, drive, cond=lambda m: True, timeout_s=10.0, what=''):
        """The first status of `drive` that meets cond; a timeout names the last one seen and
        the node's log (a failure in CI is otherwise a bare 'timed out')."""
        topic = f'{self.node_ns}/{drive}/status'
        try:
            return self.ros.wait_msg(topic, cond, timeout_s, what or f'{drive} status')
        except AssertionError as e:
            with self.ros.lock:
                last = self.ros.latest.get(topic)
            raise AssertionError(f'{e}\nlast status: {last}\n'
                                 f'node log:\n{self.node.output()[-3000:]}') from None

    def fresh_status(self, drive, what=''):
        """A status of `drive` published after this call (idle, at status_rate_hz)."""
        with self.ros.lock:
            self.ros.latest.pop(f'{self.node_ns}/{drive}/status', None)
        return self.status(drive, what=what)

    def true_topic(self, drive):
        return f'{self.sim_ns}/{drive}/true_position_steps'

    def true_steps(self, drive):
        """The simulator's position counter (the latest sample)."""
        return self.ros.wait_msg(self.true_topic(drive)).data

    def fresh_true_steps(self, drive):
        """A true position published after this call (the topic runs at 20 Hz)."""
        with self.ros.lock:
            self.ros.latest.pop(self.true_topic(drive), None)
        return self.ros.wait_msg(self.true_topic(drive)).data

    def call(self, drive, name, request=None, srv=None, timeout_s=30.0):
        """A service of one drive (default type std_srvs/Trigger)."""
        if srv is None:
            from std_srvs.srv import Trigger as srv
        return self.ros.call(srv, f'{self.node_ns}/{drive}/{name}', request, timeout_s)

    def move_to(self, drive, position, timeout_s=20.0):
        """The drive's ~/<drive>/move_to action (stepper_drivers_msgs/action/MoveTo) to
        `position` [joint units]; its result."""
        from rclpy.action import ActionClient
        from stepper_drivers_msgs.action import MoveTo
        client = ActionClient(self.ros.node, MoveTo, f'{self.node_ns}/{drive}/move_to')
        assert client.wait_for_server(timeout_sec=10)
        sent, got = threading.Event(), threading.Event()
        fut = self.ros.in_spin(client.send_goal_async, MoveTo.Goal(position=float(position)))
        fut.add_done_callback(lambda _f: sent.set())
        assert sent.wait(10) and fut.result().accepted
        res = self.ros.in_spin(fut.result().get_result_async)
        res.add_done_callback(lambda _f: got.set())
        assert got.wait(timeout_s), f'{drive}: no move_to result within {timeout_s} s'
        self.ros.in_spin(client.destroy)
        return res.result().result

    def enable(self, drive, on=True):
        from std_srvs.srv import SetBool
        r = self.call(drive, 'enable', SetBool.Request(data=on), SetBool)
        assert r.success, r.message
        return r

    def inject(self, drive, kind, code=0, value=0.0):
        """The simulator's ~/inject_fault; it must accept the fault."""
        from stepper_drivers_msgs.srv import InjectFault
        r = self.ros.call(InjectFault, self.sim_ns + '/inject_fault',
                          InjectFault.Request(drive=drive, kind=kind, code=int(code),
                                              value=float(value)))
        assert r.success, r.message
        return r

    def command(self, drive, topic, value):
        from std_msgs.msg import Float64
        self.ros.publish(Float64, f'{self.node_ns}/{drive}/{topic}', Float64(data=value))

    def set_params(self, *params):
        """Set node parameters ((name, value), ...: floats as double, else integer); returns
        the SetParameters results."""
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters
        req = SetParameters.Request()
        for name, value in params:
            v = ParameterValue()
            if isinstance(value, float):
                v.type, v.double_value = ParameterType.PARAMETER_DOUBLE, value
            else:
                v.type, v.integer_value = ParameterType.PARAMETER_INTEGER, value
            req.parameters.append(Parameter(name=name, value=v))
        return self.ros.call(SetParameters, self.node_ns + '/set_parameters', req).results


def bad_parameter_output(procs, tmp_path, vendor, old, new, timeout_s=20.0) -> list[str]:
    """Start `<vendor>_node` on config/<vendor>.yaml with `old` replaced by `new`; it must end
    with exit code 2 (a bad parameter) within timeout_s. Returns its output lines."""
    text = (CONFIG / f'{vendor}.yaml').read_text()
    assert old in text, f'{old!r} is not in config/{vendor}.yaml'
    f = tmp_path / 'bad.yaml'
    f.write_text(text.replace(old, new))
    p = procs.start('bad', [executable('stepper_drivers', f'{vendor}_node'), '--ros-args',
                            '--params-file', str(f)])
    assert p.proc.wait(timeout=timeout_s) == 2
    return p.output().strip().splitlines()


class TrajectoryGoal:
    """One goal to a node's ~/follow_joint_trajectory (control_msgs/action/FollowJointTrajectory)
    through rclpy's ActionClient, as MoveIt's simple controller manager sends it; its feedback,
    and when it was sent and when its result came (time.monotonic())."""

    def __init__(self, bench, goal):
        from control_msgs.action import FollowJointTrajectory
        from rclpy.action import ActionClient
        self.client = ActionClient(bench.ros.node, FollowJointTrajectory,
                                   f'{bench.node_ns}/follow_joint_trajectory')
        assert self.client.wait_for_server(timeout_sec=10)
        self.bench, self.feedback = bench, []
        self.status = self.result_t = self._result = None
        done, self._got = threading.Event(), threading.Event()
        self.sent_t = time.monotonic()
        # in_spin: rclpy's ActionClient races its own executor when called from another thread
        fut = bench.ros.in_spin(self.client.send_goal_async, goal,
                                feedback_callback=lambda f: self.feedback.append(f.feedback))
        fut.add_done_callback(lambda _f: done.set())
        assert done.wait(10) and fut.result().accepted
        self.handle = fut.result()

        def got(f):
            self.result_t = time.monotonic()
            self.status, self._result = f.result().status, f.result().result
            self._got.set()
        bench.ros.in_spin(self.handle.get_result_async).add_done_callback(got)

    def result(self, timeout_s):
        """The result once the goal ended (its GoalStatus in `status`)."""
        assert self._got.wait(timeout_s), f'no result within {timeout_s} s'
        self.close()
        return self._result

    def cancel(self):
        done = threading.Event()
        self.bench.ros.in_spin(self.handle.cancel_goal_async).add_done_callback(
            lambda _f: done.set())
        assert done.wait(5.0)

    def close(self):
        # in the spin thread: destroyed from another one while the executor waits on it,
        # rclpy fails the wait set ('action client pointer is invalid') and stops spinning
        self.bench.ros.in_spin(self.client.destroy)


class Track:
    """A simulator's true position (its ~/<drive>/true_position_steps at 20 Hz) with the time
    each sample arrived: when did the real axis stop?"""

    SAMPLE_S = 0.05

    def __init__(self, ros, topic):
        from std_msgs.msg import Float64
        self.samples: list[tuple[float, float]] = []
        self.lock = threading.Lock()
        self.sub = ros.node.create_subscription(Float64, topic, self._cb, 50)

    def _cb(self, msg):
        with self.lock:
            self.samples.append((time.monotonic(), msg.data))

    def still_since(self, tolerance_steps=0.5):
        """Arrival time of the first sample of the current standstill (None while moving)."""
        with self.lock:
            samples = list(self.samples)
        if len(samples) < 2 or abs(samples[-1][1] - samples[-2][1]) > tolerance_steps:
            return None
        t = samples[-1][0]
        for (t0, x0), (_t1, x1) in zip(reversed(samples[:-1]), reversed(samples)):
            if abs(x1 - x0) > tolerance_steps:
                break
            t = t0
        return t

    def wait_still(self, hold_s, timeout_s, what):
        """Wait for a standstill that lasted hold_s; return when it began."""
        def check():
            t = self.still_since()
            return t if t is not None and time.monotonic() - t >= hold_s else None
        return wait_for(check, timeout_s, what)


# Two DDS hops lie on the measured path (the test's command to the node, the simulator's
# sample to the test): rclpy publish -> callback p99 is 1-2 ms idle and up to 10 ms on this
# 2-core machine under a full test run (docs/benchmarks.md, "middleware floor").
MIDDLEWARE_S = 0.02


def watchdog_bound_s(timeout_s, rate_hz, velocity, deceleration, transaction_s):
    """When a velocity run must have stopped after its last command: the watchdog's
    command_timeout_s, two poll periods, the stop ramp and the one transaction in flight, plus
    one true-position sample (the standstill is seen at the first unchanged sample) and the
    two middleware hops of the measurement."""
    return (timeout_s + 2.0 / rate_hz + abs(velocity) / deceleration + transaction_s
            + Track.SAMPLE_S + MIDDLEWARE_S)
