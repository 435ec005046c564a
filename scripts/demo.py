#!/usr/bin/env python3
"""The README's main command: every simulated drive family and its node, driven through ROS.

Every vendor of the vendor table (DEMOS) at once (in parallel): its simulator and its node (the
params files in config/, on a free port or pty), then per drive, also in parallel: enable, home,
the moves of `targets`; then, per bus, one two-axis trajectory through ~/follow_joint_trajectory
(both axes arrive at each point together); then per drive a velocity run that the node's watchdog
stops (no more velocity_command after 1 s), disable. A live status table shows every drive
meanwhile; at the end a plot of commanded versus actual position of every drive over time is
written (default out/demo_positions.png), and one of each bus's two-axis path, actual against
commanded (demo_positions_paths.png beside it). Exits 0 when every step worked, leaving no process
behind. Run it with scripts/demo.sh (which bootstraps the workspace first).
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import sys
import tempfile
import threading
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from std_msgs.msg import Float64
from std_srvs.srv import SetBool, Trigger
from stepper_drivers.cli import view
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers.vendors import table as vendor_table
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.harness import CONFIG, ROOT, Proc, executable, free_port
import yaml

# The moves of a vendor's drives; DEFAULT_MOVES for a vendor not named here.
DEFAULT_MOVES = dict(targets=(3.0, -2.0, 0.0), velocity=6.0)
MOVES = {
    # 2000 step/rev: targets within the 1e-3 rad check (-2.0 rad would be 0.0012 rad off)
    'xmind_k': dict(targets=(3.0, -4.0, 0.0), velocity=6.0),
}


def _link_is_path(row: vendor_table.VendorRow) -> bool:
    """The link of a serial line is a path (the simulator's pty symlink); of a TCP server or a CAN
    broker, a port number: as the node's params file gives it."""
    value = next(iter(yaml.safe_load((CONFIG / row.params_file).read_text()).values()))
    value = value['ros__parameters']
    for part in row.link_param.split('.'):
        value = value[part]
    return isinstance(value, str)


# Every vendor of the table: simulator, node, the parameter that carries the link address, what
# it is (link 'path' or 'port'), the helpers the simulator needs (the CAN broker: started first on
# that port), and the moves.
DEMOS = {row.key: dict(sim=row.sim, node=row.node, link_param=row.link_param,
                       link='path' if _link_is_path(row) else 'port', helpers=row.sim_helpers,
                       **MOVES.get(row.key, DEFAULT_MOVES))
         for row in vendor_table.ROWS}

# Participants announce every 0.3 s instead of 3 s: the demo's client sees the nodes at once.
FAST_DISCOVERY = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(CONFIG / 'fastdds_fast_discovery.xml')}
DEMO_TIME_LIMIT_S = 100.0      # the README promises under two minutes, bootstrap included
POSITION_TOLERANCE = 1e-3      # rad: every target of DEMOS is this close to a whole step
VELOCITY_RUN_S = 1.0
RECONNECT_WAIT_S = 15.0     # a node retries a lost drive with back-off (reconnect_period_s x 1..8)
VELOCITY_COMMAND_PERIOD_S = 0.1     # 10 Hz, well inside command_timeout_s (0.5 s in config/)
# The two-axis trajectory of every bus: (time_from_start [s], first joint, second joint) [rad],
# from the last target 0.0; within every vendor's max_velocity and max_acceleration.
TRAJECTORY = ((1.5, 1.5, 0.5), (3.0, 0.5, 2.0), (4.5, 0.0, 0.0))
LOG_LINES_SHOWN = 14


class Console:
    """Log lines and the live status table, without the two getting in each other's way.

    On a terminal the screen is redrawn: the table, then the last log lines. Elsewhere (a pipe,
    CI) log lines are printed as they come and the table every `table_period_s`.
    """

    def __init__(self, demo: 'Demo', table_period_s: float = 5.0):
        self.demo = demo
        self.tty = sys.stdout.isatty()
        self.lock = threading.Lock()
        self.lines: list[str] = []
        self.table_period_s = table_period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with self.lock:
            print(self._table(), flush=True)

    def log(self, text: str) -> None:
        stamp = f'{time.monotonic() - self.demo.t0:6.1f} s  '
        with self.lock:
            self.lines.append(stamp + text)
            if not self.tty:
                print(stamp + text, flush=True)

    def _table(self) -> str:
        rows = [view.row(label, *self.demo.latest(label)) for label in self.demo.drive_labels()]
        return view.table(rows)

    def _run(self) -> None:
        period = 0.25 if self.tty else self.table_period_s
        while not self._stop.wait(period):
            with self.lock:
                if not self.demo.drive_labels():
                    continue
                if self.tty:
                    title = (f'stepper_drivers demo  {time.monotonic() - self.demo.t0:5.1f} s   '
                             '(live status of every drive; log below)')
                    text = '\n'.join([title, self._table(), ''] + self.lines[-LOG_LINES_SHOWN:])
                    sys.stdout.write(view.CLEAR_SCREEN + text + '\n')
                    sys.stdout.flush()
                else:
                    print(self._table() + '\n', flush=True)


class Demo:
    def __init__(self, ros: RosClient, log_dir: pathlib.Path):
        self.ros = ros
        self.log_dir = log_dir
        self.t0 = time.monotonic()
        self.wall0 = time.time()
        self.deadline = self.t0 + DEMO_TIME_LIMIT_S
        self.procs: list[Proc] = []
        self.failures: list[str] = []
        self.lock = threading.Lock()
        self.console = Console(self)
        # per drive label ('xplus_mt_node/axis1'): status history, commands, phases
        self.drives: dict[str, dict] = {}
        # per vendor: the two drive labels, the trajectory's start time and its end
        self.trajectories: dict[str, dict] = {}

    # ------------------------------------------------------------------------- bookkeeping
    def say(self, text: str) -> None:
        self.console.log(text)

    def check(self, ok: bool, what: str) -> bool:
        if not ok:
            with self.lock:
                self.failures.append(what)
            self.say(f'FAILED: {what}')
        return ok

    def drive_labels(self) -> list[str]:
        with self.lock:
            return sorted(self.drives)

    def latest(self, label: str) -> tuple[DriveStatus | None, float]:
        with self.lock:
            d = self.drives[label]
            if not d['status']:
                return None, math.inf
            return d['status'][-1][1], time.monotonic() - d['status'][-1][0]

    def track(self, vendor: str, node: str, drive: str) -> str:
        """Subscribe to a drive's status, keeping (receive time, message) for the plot."""
        label = f'{node}/{drive}'
        with self.lock:
            self.drives[label] = dict(vendor=vendor, status=[], commands=[], phases=[])

        def on_status(msg: DriveStatus, label=label) -> None:
            with self.lock:
                self.drives[label]['status'].append((time.monotonic(), msg))
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        self.ros.node.create_subscription(
            DriveStatus, f'/{label}/status', on_status,
            QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        return label

    def commanded(self, label: str, position: float) -> None:
        with self.lock:
            self.drives[label]['commands'].append((time.monotonic(), position))

    def phase(self, label: str, name: str, start: float, end: float) -> None:
        with self.lock:
            self.drives[label]['phases'].append((name, start, end))

    def wait_status(self, label: str, cond, timeout_s: float, what: str,
                    required: bool = True) -> DriveStatus | None:
        deadline = min(time.monotonic() + timeout_s, self.deadline)
        while True:
            msg, _age = self.latest(label)
            if msg is not None and cond(msg):
                return msg
            if time.monotonic() >= deadline:
                if required:
                    self.check(False, f'{label}: {what} not seen within {timeout_s:g} s')
                return msg
            time.sleep(0.02)   # poll the subscription's latest message

    # ------------------------------------------------------------------------------ start-up
    def start(self, vendor: str, spec: dict) -> tuple[str, list[str]]:
        port = str(free_port()) if spec['link'] != 'path' else str(self.log_dir / vendor)
        for name, *args in spec['helpers']:
            # on the demo's own port; a helper says 'listening' once it takes connections
            if '--port' in args:
                args[args.index('--port') + 1] = port
            helper = self.proc([executable('stepper_sim', name), *args], f'{vendor}_{name}')
            helper.wait_line('listening', 10.0)
        sim = self.proc([executable('stepper_sim', spec['sim']), '--ros-args', '--params-file',
                         str(CONFIG / f'{vendor}_sim.yaml'), '-p',
                         f"{spec['link_param']}:={port}"], spec['sim'])
        sim.wait_line('ready', 30.0)
        self.proc([executable('stepper_drivers', spec['node']), '--ros-args', '--params-file',
                   str(CONFIG / f'{vendor}.yaml'), '-p', f"{spec['link_param']}:={port}"],
                  spec['node'])
        drives = self._drive_names(vendor)
        labels = [self.track(vendor, spec['node'], d) for d in drives]
        for label in labels:
            self.wait_status(label, lambda m: m.connected, 30.0, 'connected')
        where = port if spec['link'] == 'path' else f'127.0.0.1:{port}'
        self.say(f'[{vendor}] simulator and node up on {where}; drives: {", ".join(drives)}')
        return '/' + spec['node'], drives

    def proc(self, args: list[str], name: str) -> Proc:
        p = Proc(args, self.log_dir, name, FAST_DISCOVERY)
        with self.lock:
            self.procs.append(p)
        return p

    @staticmethod
    def _drive_names(vendor: str) -> list[str]:
        import yaml
        params = yaml.safe_load((CONFIG / f'{vendor}.yaml').read_text())
        return list(next(iter(params.values()))['ros__parameters']['drives'])

    # ------------------------------------------------------------------------ the sequence
    def connected(self, label: str) -> None:
        """A drive can drop off its line for a moment (a slow machine starves the simulator):
        the node refuses commands then, so each step waits for the link first."""
        msg, _age = self.latest(label)
        if msg is None or not msg.connected:
            self.say(f'[{label}] waiting for the link to come back')
            self.wait_status(label, lambda m: m.connected, RECONNECT_WAIT_S, 'connected')

    def service(self, label: str, srv_type, name: str, request=None, timeout_s: float = 30.0):
        for attempt in (1, 2):
            self.connected(label)
            try:
                resp = self.ros.call(srv_type, f'/{label}/{name}', request, timeout_s)
            except AssertionError as e:
                self.check(False, f'{label}: {e}')
                return None
            if resp.success or 'DISCONNECTED' not in resp.message or attempt == 2:
                break
            self.say(f'[{label}] {name}: {resp.message}; again once the link is back')
            # the last status seen may predate the loss: see the loss first, if it shows
            self.wait_status(label, lambda m: not m.connected, 2.0, 'link loss', required=False)
            self.wait_status(label, lambda m: m.connected, RECONNECT_WAIT_S, 'connected')
        self.say(f'[{label}] {name}: {resp.message}')
        self.check(resp.success, f'{label} {name}: {resp.message}')
        return resp

    def run_drive(self, label: str, spec: dict, barrier: threading.Barrier | None = None,
                  pair: list[str] | None = None) -> None:
        self.say(f'[{label}] enable')
        if not self.service(label, SetBool, 'enable', SetBool.Request(data=True)):
            return
        t = time.monotonic()
        self.service(label, Trigger, 'home')
        self.phase(label, 'home', t, time.monotonic())
        for target in spec['targets']:
            self.say(f'[{label}] move to {target:+.3f} rad')
            self.connected(label)
            self.commanded(label, target)
            self.ros.publish(Float64, f'/{label}/position_command', Float64(data=target))
            st = self.wait_status(label, lambda m, t=target: m.fault or (
                not m.moving and abs(m.position - t) < POSITION_TOLERANCE), 20.0,
                f'position {target:+.3f}')
            if st is not None:
                self.check(abs(st.position - target) < POSITION_TOLERANCE and not st.fault,
                           f'{label} at {st.position:.4f}, expected {target}')
        if barrier is not None:
            self.sync(barrier, label)           # every drive of the bus is done with its moves
            if pair and label == pair[0]:
                self.run_trajectory(spec['vendor'], pair)
            self.sync(barrier, label)
        v = spec['velocity']
        self.say(f'[{label}] velocity {v} rad/s for {VELOCITY_RUN_S:g} s, then no more '
                 'commands: the node watchdog stops it')
        self.commanded(label, math.nan)
        t = time.monotonic()
        while time.monotonic() < t + VELOCITY_RUN_S:
            self.ros.publish(Float64, f'/{label}/velocity_command', Float64(data=v))
            time.sleep(VELOCITY_COMMAND_PERIOD_S)  # the command rate of this demo
        st = self.wait_status(label, lambda m: m.fault or not m.moving, 10.0,
                              'standstill after the watchdog')
        self.phase(label, 'velocity', t, time.monotonic())
        if st is not None and self.check(not st.moving and not st.fault,
                                         f'{label} still moving after the watchdog'):
            self.say(f'[{label}] stopped by the watchdog at {st.position:+.3f} rad; disable')
        self.service(label, SetBool, 'enable', SetBool.Request(data=False))

    def run_vendor(self, vendor: str, spec: dict) -> None:
        t = time.monotonic()
        try:
            ns, drives = self.start(vendor, spec)
            labels = [f'{ns[1:]}/{d}' for d in drives]
            barrier = threading.Barrier(len(labels))
            spec = dict(spec, vendor=vendor)
            threads = [threading.Thread(target=self.guard, args=(
                self.run_drive, label, spec, barrier, labels[:2]), daemon=True)
                for label in labels]
            for th in threads:
                th.start()
            for th in threads:
                th.join(max(self.deadline - time.monotonic(), 0.1))
        except (AssertionError, FileNotFoundError) as e:
            self.check(False, f'{vendor}: {e}')
        self.say(f'[{vendor}] done in {time.monotonic() - t:.1f} s')

    def sync(self, barrier: threading.Barrier, label: str) -> None:
        try:
            barrier.wait(max(self.deadline - time.monotonic(), 0.1))
        except threading.BrokenBarrierError:
            self.check(False, f'{label}: the other drives of the bus did not get there')
            raise

    def run_trajectory(self, vendor: str, labels: list[str]) -> None:
        """One two-axis trajectory through the node's follow_joint_trajectory action."""
        from builtin_interfaces.msg import Duration
        from control_msgs.action import FollowJointTrajectory
        from rclpy.action import ActionClient
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
        joints = [self.latest(label)[0].joint_name for label in labels]
        node = labels[0].split('/')[0]
        msg = JointTrajectory(joint_names=joints)
        for t, a, b in TRAJECTORY:
            msg.points.append(JointTrajectoryPoint(positions=[a, b], time_from_start=Duration(
                sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))))
        self.say(f'[{vendor}] two-axis trajectory {joints}: '
                 + ', '.join(f'({a:+.1f}, {b:+.1f}) at {t:g} s' for t, a, b in TRAJECTORY))
        # Not destroyed here: an action client destroyed while the spin thread runs, even by a
        # task of its own executor, can still be in the wait set that executor is working
        # through, and rclpy then takes from a freed handle (TypeError in take_goal_response)
        # and the spin thread dies for every vendor. It goes with the node, after the spin
        # thread stopped (RosClient.close).
        client = ActionClient(self.ros.node, FollowJointTrajectory,
                              f'/{node}/follow_joint_trajectory')
        if not self.check(client.wait_for_server(timeout_sec=10),
                          f'{vendor}: no follow_joint_trajectory'):
            return
        start = time.monotonic()
        goal = self.ros.in_spin(client.send_goal_async,
                                FollowJointTrajectory.Goal(trajectory=msg))
        handle = self._future(goal, 10.0)
        if not self.check(handle is not None and handle.accepted,
                          f'{vendor}: trajectory goal not accepted'):
            return
        with self.lock:
            self.trajectories[vendor] = dict(labels=labels, start=start, end=None)
        result = self._future(self.ros.in_spin(handle.get_result_async),
                              TRAJECTORY[-1][0] + 15.0)
        end = time.monotonic()
        with self.lock:
            self.trajectories[vendor]['end'] = end
        for label in labels:
            self.phase(label, 'trajectory', start, end)
        ok = result is not None and result.result.error_code == 0
        text = result.result.error_string if result is not None else 'no result'
        if self.check(ok, f'{vendor}: trajectory: {text}'):
            self.say(f'[{vendor}] trajectory done: {text}')

    def _future(self, fut, timeout_s: float):
        done = threading.Event()
        fut.add_done_callback(lambda _f: done.set())
        return fut.result() if done.wait(timeout_s) else None

    def guard(self, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as e:  # noqa: BLE001 - a failed step must not hang the demo
            self.check(False, f'{args[0]}: {type(e).__name__}: {e}')

    def stop_all(self) -> None:
        with self.lock:
            procs = list(reversed(self.procs))
            self.procs.clear()
        nodes = [p for p in procs if p.name.endswith('_node')]
        others = [p for p in procs if not p.name.endswith('_node')]
        for group in (nodes, others):          # nodes first: they stop and disable the drives
            stoppers = [threading.Thread(target=self._stop_one, args=(p,)) for p in group]
            for th in stoppers:
                th.start()
            for th in stoppers:
                th.join()

    def _stop_one(self, p: Proc) -> None:
        try:
            code = p.stop()
        except AssertionError as e:
            self.check(False, str(e).splitlines()[0])
            return
        self.check(code == 0, f'{p.name} exit code {code}')


# ---------------------------------------------------------------------------------- the plot
PHASES = {'home': ('tab:gray', 'homing'),
          'trajectory': ('tab:green', 'two-axis trajectory'),
          'velocity': ('tab:orange', 'velocity run, watchdog stop')}


def plot_paths(demo: Demo, path: pathlib.Path) -> None:
    """Each bus's two-axis trajectory: the path of the two joints, actual (from the status of
    both drives, the second one interpolated at the first one's times) against commanded (the
    straight segments between the points, which both axes start and end together)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import numpy as np

    with demo.lock:
        runs = {v: dict(r) for v, r in demo.trajectories.items() if r.get('end')}
    if not runs:
        raise RuntimeError('no trajectory ran')
    fig, axes = plt.subplots(1, len(runs), figsize=(4.2 * len(runs), 4.0), squeeze=False)
    for ax, (vendor, run) in zip(axes[0], sorted(runs.items())):
        with demo.lock:
            series = [[(t, m.position) for t, m in demo.drives[label]['status']
                       if run['start'] <= t <= run['end']] for label in run['labels']]
            estimated = any(m.position_estimated for label in run['labels']
                            for t, m in demo.drives[label]['status']
                            if run['start'] <= t <= run['end'])
            joints = [demo.drives[label]['status'][-1][1].joint_name for label in run['labels']]
        (t1, x), (t2, y) = [tuple(zip(*s)) if s else ((), ()) for s in series]
        ax.plot([0.0] + [a for _t, a, _b in TRAJECTORY], [0.0] + [b for _t, _a, b in TRAJECTORY],
                '--o', color='tab:red', lw=1.2, ms=4, label='commanded (points)')
        if t1 and t2:
            ax.plot(x, np.interp(t1, t2, y), '-', color='tab:blue', lw=1.4, label='actual')
        # X-MIND K: no position while it moves (§3), the node estimates it between polls
        ax.set_title(vendor + (' (positions estimated while moving)' if estimated else ''),
                     fontsize=9)
        ax.set_xlabel(f'{joints[0]} [rad]', fontsize=8)
        ax.set_ylabel(f'{joints[1]} [rad]', fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle('two-axis trajectories: actual path against the commanded one', fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot(demo: Demo, path: pathlib.Path) -> None:
    """Commanded (dashed steps) and actual (solid) position of every drive over time."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    labels = demo.drive_labels()
    cols = 3
    rows = max(1, math.ceil(len(labels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.2 * rows), squeeze=False,
                             sharex=True)
    t_end = time.monotonic() - demo.t0
    for ax, label in zip(axes.flat, labels):
        d = demo.drives[label]
        t = [r - demo.t0 for r, _m in d['status']]
        pos = [m.position for _r, m in d['status']]
        joint = d['status'][-1][1].joint_name if d['status'] else ''
        ax.plot(t, pos, '-', color='tab:blue', lw=1.4, label='actual (status)')
        if d['commands']:
            ct = [c - demo.t0 for c, _p in d['commands']] + [t_end]
            cp = [p for _c, p in d['commands']] + [d['commands'][-1][1]]
            ax.step(ct, cp, where='post', ls='--', color='tab:red', lw=1.2,
                    label='commanded position')
        for name, start, end in d['phases']:
            color, text = PHASES[name]
            ax.axvspan(start - demo.t0, end - demo.t0, color=color, alpha=0.18, label=text)
        ax.set_title(f"{d['vendor']}: {label} ({joint})", fontsize=9)
        ax.set_ylabel('position [rad]', fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    for ax in axes.flat[len(labels):]:
        ax.axis('off')
    for ax in axes[-1]:
        ax.set_xlabel('time since the demo started [s]', fontsize=8)
    handles, names = axes.flat[0].get_legend_handles_labels()
    seen = dict(zip(names, handles))
    fig.suptitle('stepper_drivers demo: commanded vs actual position of every drive',
                 fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.6 / fig.get_figheight()))
    fig.legend(seen.values(), seen.keys(), loc='upper center', ncol=4, fontsize=8,
               frameon=False, bbox_to_anchor=(0.5, 1 - 0.3 / fig.get_figheight()))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', action='append', choices=sorted(DEMOS),
                    help='run only this vendor (repeatable); default: all')
    ap.add_argument('--sequential', action='store_true',
                    help='one vendor after the other (slower; for a machine short of CPU)')
    ap.add_argument('--plot', default=str(ROOT / 'out' / 'demo_positions.png'),
                    help='where the plot goes (default out/demo_positions.png)')
    args = ap.parse_args()
    for key, value in FAST_DISCOVERY.items():
        os.environ.setdefault(key, value)
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='stepper_demo_'))
    ros = RosClient('stepper_demo')
    demo = Demo(ros, log_dir)
    vendors = args.vendor or list(DEMOS)
    demo.say(f'starting {", ".join(vendors)} (simulators and nodes; logs in {log_dir})')
    demo.console.start()
    try:
        runners = [threading.Thread(target=demo.run_vendor, args=(v, DEMOS[v]), daemon=True)
                   for v in vendors]
        for th in runners:
            th.start()
            if args.sequential:
                th.join(max(demo.deadline - time.monotonic(), 0.1))
        for th in runners:
            th.join(max(demo.deadline - time.monotonic(), 0.1))
            if th.is_alive():
                demo.check(False, f'time limit of {DEMO_TIME_LIMIT_S:g} s reached')
                break
    except KeyboardInterrupt:
        demo.check(False, 'interrupted')
    finally:
        demo.console.stop()
        demo.say('stopping every node (stop, disable) and simulator')
        demo.stop_all()
        for p in demo.procs:
            p.kill()
        ros.close()
    plot_path = pathlib.Path(args.plot)
    paths_path = plot_path.with_name(plot_path.stem + '_paths' + plot_path.suffix)
    try:
        plot(demo, plot_path)
        print(f'plot of commanded vs actual position: {plot_path}', flush=True)
        plot_paths(demo, paths_path)
        print(f'plot of the two-axis paths: {paths_path}', flush=True)
    except Exception as e:  # noqa: BLE001 - the drives' result stands without the plot
        demo.failures.append(f'plot: {type(e).__name__}: {e}')
    took = time.monotonic() - demo.t0
    if demo.failures:
        print(f'demo FAILED after {took:.0f} s ({len(demo.failures)}): '
              + '; '.join(demo.failures) + f'\nprocess logs: {log_dir}', file=sys.stderr)
        return 1
    print(f'demo OK in {took:.0f} s: every drive enabled, homed, moved, every bus followed a '
          f'two-axis trajectory, every drive stopped by its watchdog. Process logs: {log_dir}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
