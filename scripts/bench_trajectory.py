#!/usr/bin/env python3
"""Trajectory benchmark (issue 12): arrival spread at the waypoints and path error, per bus.

Every part is a process of its own (stepper_sim.harness): the vendor's simulator with its line
timing on (RD4 and X-MIND K: `line_timing:=true`, the baud rate's character times; X-PLUS MT:
`line_timing:=true`, 2 ms reply latency; Vector Step: the socketcand broker) and its true
positions (`~/<drive>/true_position_steps`) at `--sample-rate` (200 Hz: 5 ms), the node with its
config/<vendor>.yaml, and this script as the ROS client. The first two drives are enabled and N
two-axis trajectories of 3-4 points go through `~/follow_joint_trajectory`, each starting at a
known time (header.stamp 0.5 s ahead) and checked against the joints' limits with the node's own
planner (trajectory.plan) before it is sent. Measured on the simulators' true positions (steps
to rad with the drive's steps_per_rev, gear_ratio and unit: units.UnitConversion), stamped when
they arrive here (CLOCK_MONOTONIC; one DDS hop, ~1 ms, after the simulator read them):

- arrival at each waypoint: per axis, the first sample after the previous waypoint's time
  within `--band` (0.5 %) of the axis's own segment distance (at least 1 step) of the waypoint.
  A band proportional to the distance is entered at the same moment by every axis of a
  synchronized segment (their profiles are one curve scaled), so the spread is not biased by
  the axes' speeds. Spread: max - min over the axes that move in the segment. Each arrival is
  given against the waypoint's time and against the planned profile's own entry into the band
  (the plan: trajectory.plan from the start positions, sampled as follow.Run.desired_steps).
- path error: every sample in a segment's time window, the distance of the point (joint1,
  joint2) [rad] from the commanded straight path (that segment, or the one before it for the
  corner), max and RMS, also in % of the segment's length.
- following error: the distance of the sample from the planned profile at the same time (the
  node plans the same from its own polled start, and retimes a move sent late for the time left:
  a little of what is counted here is that retiming), max and RMS, % of the segment's length;
  and, second source, the action's feedback (10 Hz: the node's desired minus its polled or
  estimated position).

Goals: spread < one poll period (1 / publish_rate_hz) + one line transaction; Vector Step:
following error < 2 % of the segment length. The line transaction is measured here on the same
simulator before the node starts (X-PLUS MT: pymodbus FC03 1001 x2 round trip; RD4: pymodbus FC04
0x00 x8; X-MIND K: pyserial 01QA; the RD4 and X-MIND K figures include the line's silences: the
time per transaction of a loop); Vector Step: the SDO round trip on the broker, 0.3 ms, from
docs/benchmarks.md (command-path benchmark).

Vector Step runs twice: with config/vector_step.yaml (SYNC every 0.1 s: synchronized point-to-point
moves in profile position) and with `-p can.sync_period_s:=0.01` on the node (`--vector-sync-period
S ...`; the node streams a point every SYNC period in interpolated position; the simulator
follows the SYNC frames it sees and has no such parameter). The mode the drives were in while
following (DriveStatus.mode) and any node log line about interpolation are reported.

Run: source scripts/env.sh && python scripts/bench_trajectory.py [--vendor rd4 ...]
     [--trajectories N] [--sample-rate HZ] [--band F] [--vector-sync-period [S ...]]
     [--json out.json]            (everything: about 100 s)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import statistics
import sys
import tempfile
import threading
import time
from typing import Any

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from bench_command_path import (bare_rate, load_params, machine, reserve_domain,  # noqa: E402
                                running)
from builtin_interfaces.msg import Duration, Time  # noqa: E402
from control_msgs.action import FollowJointTrajectory  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402
from stepper_drivers.cli.ros_client import RosClient  # noqa: E402
# the one trapezoid formula of the node (follow.Run.desired_steps uses it); Run itself needs
# the node's live axes
from stepper_drivers.trajectory import along as _along  # noqa: E402
from stepper_drivers.trajectory import JointLimits, TrajectoryError, build, plan  # noqa: E402
from stepper_drivers.units import UnitConversion  # noqa: E402
from stepper_drivers.vendors.xplus_mt import XplusMtDrive  # noqa: E402
from stepper_drivers_msgs.msg import DriveStatus  # noqa: E402
from stepper_sim.harness import CONFIG, Proc, executable, free_port, wait_for  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

DRIVES = ('axis1', 'axis2')
LEAD_S = 0.5                   # header.stamp this far ahead: the start time is known here
VECTOR_GOAL = 0.02             # following error < 2 % of the segment length
# docs/benchmarks.md, "Command path through the bus owner": SDO round trip on the broker (the
# longest transaction the Vector Step node makes; a move is RxPDO frames, no answer)
VECTOR_TRANSACTION_S = 0.0003

# Trajectories (time_from_start [s], joint1, joint2) [rad], every axis moving in every segment;
# one after the other, each from where the one before ended; times x the vendor's time_scale.
SHAPES = (
    ((1.0, 2.0, 1.0), (2.0, 0.5, 2.5), (3.0, 2.5, 0.5)),
    ((1.0, -1.0, 2.0), (2.0, 1.5, 0.5), (3.0, -0.5, -1.5), (4.0, 0.5, -0.5)),
    ((1.0, 3.0, 1.0), (2.0, 1.0, -1.5), (3.0, 0.0, 0.5)),
)


@dataclasses.dataclass
class Spec:
    key: str
    title: str
    line: str
    link_param: str
    link: str                   # 'tcp' (a free port), 'path' (pty symlink), 'broker' (CAN)
    sim_args: tuple[str, ...]
    time_scale: float = 1.0


VENDORS = {
    'xplus_mt': Spec('xplus_mt', 'X-PLUS MT', 'Modbus TCP, simulator with 2 ms reply latency',
                     'port', 'tcp', ('line_timing:=true',)),
    'rd4': Spec('rd4', 'Lika RD4', 'Modbus RTU 19200 8N2, simulator line timing', 'port', 'path',
                ('line_timing:=true',)),
    # 9600 baud and a busy drive answers nothing (§3): a move's strings take ~0.1 s per axis
    'xmind_k': Spec('xmind_k', 'X-MIND K', 'ASCII 9600 8N1, simulator line timing', 'port',
                    'path', ('line_timing:=true',), time_scale=2.0),
    'vector_step': Spec('vector_step', 'Vector Step', 'CANopen, socketcand broker', 'can.port',
                        'broker', ()),
}


# --------------------------------------------------------------------------------- recording
class Recorder:
    """Arrival-stamped messages of one topic (CLOCK_MONOTONIC when the callback ran)."""

    def __init__(self, ros: RosClient, msg_type, topic: str, value=lambda m: m):
        self.samples: list[tuple[float, Any]] = []
        self.lock = threading.Lock()
        self.value = value
        self.sub = ros.node.create_subscription(msg_type, topic, self._cb, 500)

    def _cb(self, msg) -> None:
        with self.lock:
            self.samples.append((time.monotonic(), self.value(msg)))

    def between(self, t0: float, t1: float) -> list[tuple[float, Any]]:
        with self.lock:
            return [(t, v) for t, v in self.samples if t0 <= t <= t1]

    def last_before(self, t: float) -> Any:
        with self.lock:
            older = [v for ts, v in self.samples if ts <= t]
        return older[-1] if older else None


def send_goal(ros: RosClient, node: str, goal, on_feedback, timeout_s: float):
    """One follow_joint_trajectory goal; its result (rclpy ActionClient through ros.in_spin:
    see RosClient.in_spin)."""
    from rclpy.action import ActionClient
    client = ActionClient(ros.node, FollowJointTrajectory, f'/{node}/follow_joint_trajectory')
    try:
        if not client.wait_for_server(timeout_sec=10):
            raise RuntimeError(f'/{node}/follow_joint_trajectory not available')

        def wait(fut, t):
            done = threading.Event()
            fut.add_done_callback(lambda _f: done.set())
            if not done.wait(t):
                raise RuntimeError(f'no answer from /{node}/follow_joint_trajectory in {t:g} s')
            return fut.result()
        handle = wait(ros.in_spin(client.send_goal_async, goal,
                                  feedback_callback=lambda f: on_feedback(f.feedback)), 10.0)
        if not handle.accepted:
            raise RuntimeError('goal not accepted')
        return wait(ros.in_spin(handle.get_result_async), timeout_s).result
    finally:
        ros.in_spin(client.destroy)


# ---------------------------------------------------------------------------- line transaction
def transaction_s(spec: Spec, link: str) -> tuple[float, str]:
    """(seconds, what) of one line transaction, measured on the simulator before the node
    opens the link (the serial ptys take one master)."""
    if spec.key == 'vector_step':
        return VECTOR_TRANSACTION_S, 'SDO round trip on the broker, docs/benchmarks.md'
    if spec.key == 'xplus_mt':
        from pymodbus.client import ModbusTcpClient
        c = ModbusTcpClient('127.0.0.1', port=int(link), timeout=1)
        assert c.connect(), f'no Modbus TCP server on {link}'
        times = []
        try:
            for _ in range(100):
                t = time.monotonic()
                r = c.read_holding_registers(1001, count=2, device_id=1)
                times.append(time.monotonic() - t)
                assert not r.isError(), r
        finally:
            c.close()
        return statistics.median(times), 'FC03 1001 x2 round trip (pymodbus), median of 100'
    what = {'rd4': 'FC04 0x00 x8 loop (pymodbus), with t3.5',
            'xmind_k': '01QA loop (pyserial), with the §3 margins'}[spec.key]
    return 1.0 / bare_rate(spec, link, 2.0), what


# ----------------------------------------------------------------------------------- analysis
def seg_distance(p, a, b) -> float:
    """Distance of point p from the segment a-b (2-D)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    n2 = dx * dx + dy * dy
    f = 0.0 if n2 == 0 else min(1.0, max(0.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / n2))
    return math.hypot(p[0] - a[0] - f * dx, p[1] - a[1] - f * dy)


def interp(samples: list[tuple[float, float]], t: float) -> float:
    """Linear interpolation of (t, x) samples at t (held at the ends)."""
    if t <= samples[0][0]:
        return samples[0][1]
    for (t0, x0), (t1, x1) in zip(samples, samples[1:]):
        if t <= t1:
            return x0 if t1 == t0 else x0 + (x1 - x0) * (t - t0) / (t1 - t0)
    return samples[-1][1]


def first_in_band(samples, t_from: float, t_to: float, target: float, band: float
                  ) -> tuple[float | None, float]:
    """(time of the first sample in t_from..t_to within band of target, or None; the closest
    approach in that window)."""
    closest = math.inf
    for t, x in samples:
        if t_from <= t <= t_to:
            if abs(x - target) <= band:
                return t, abs(x - target)
            closest = min(closest, abs(x - target))
    return None, closest


def on_time(samples: list[tuple[float, float]], period_s: float) -> list[tuple[float, float]]:
    """The samples that arrived one publishing period (0.3..2 x) after the one before: after a
    stall of this process or of DDS, samples come in a burst, stamped late (a 100 ms stall once
    made 180 mrad of following error out of nothing); those and the first after a gap go."""
    out = []
    for (t0, _x0), (t1, x1) in zip(samples, samples[1:]):
        if 0.3 * period_s <= t1 - t0 <= 2.0 * period_s:
            out.append((t1, x1))
    return out


def rms(xs: list[float]) -> float:
    return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else float('nan')


def analyse(points_rad, start_t: float, start_steps: dict, convs: dict, limits: dict,
            joints: list[str], samples: dict, feedback: list, band_frac: float) -> dict:
    """Figures of one trajectory. points_rad: [(t, x1, x2)]; samples: drive -> [(t, steps)]."""
    traj = build(joints, [p[0] for p in points_rad],
                 [[convs[d].to_steps(x) for d, x in zip(DRIVES, p[1:])] for p in points_rad],
                 joints)
    segments = plan(traj, {j: start_steps[d] for j, d in zip(joints, DRIVES)},
                    {j: limits[d] for j, d in zip(joints, DRIVES)})

    def planned(t):          # rad, per drive: follow.Run.desired_steps without the node
        want = {j: start_steps[d] for j, d in zip(joints, DRIVES)}
        for seg in segments:
            if t - start_t <= seg.start_s:
                break
            tau = min(t - start_t, seg.end_s) - seg.start_s
            for m in seg.moves:
                want[m.joint] = _along(want[m.joint], m.target_steps, m.velocity_steps_s,
                                       m.acceleration_steps_s2, tau)
        return [convs[d].from_steps(want[j]) for j, d in zip(joints, DRIVES)]
    rad = {d: [(t, convs[d].from_steps(x)) for t, x in samples[d]] for d in DRIVES}
    corners = [tuple(convs[d].from_steps(start_steps[d]) for d in DRIVES)] + \
        [(p[1], p[2]) for p in points_rad]
    times = [0.0] + [p[0] for p in points_rad]
    waypoints, path_all, follow_all = [], [], []
    for k in range(1, len(corners)):
        a, b = corners[k - 1], corners[k]
        length = math.hypot(b[0] - a[0], b[1] - a[1])
        t_prev, t_wp = start_t + times[k - 1], start_t + times[k]
        # an axis may take the next segment's move before it arrived (late): search until
        # the next waypoint's time
        t_next = start_t + (times[k + 1] if k + 1 < len(times) else times[k] + 2.0)
        arrivals, late, late_plan, missed = {}, {}, {}, {}
        for i, d in enumerate(DRIVES):
            dist = abs(b[i] - a[i])
            if dist == 0:
                continue
            band = max(band_frac * dist, 1.0 / convs[d].steps_per_unit)
            t_arr, closest = first_in_band(rad[d], t_prev, t_next, b[i], band)
            if t_arr is None:
                missed[d] = closest
            # the plan's own entry into the band, on a 1 ms grid
            t_plan = next((t_prev + n * 0.001 for n in range(int((t_wp - t_prev) / 0.001) + 2)
                           if abs(planned(t_prev + n * 0.001)[i] - b[i]) <= band), t_wp)
            arrivals[d] = t_arr
            if t_arr is not None:
                late[d] = t_arr - t_wp
                late_plan[d] = t_arr - t_plan
        seen = [t for t in arrivals.values() if t is not None]
        spread = max(seen) - min(seen) if len(seen) == len(arrivals) and seen else None
        # samples of this segment's window: axis2 interpolated at axis1's times (same tick)
        path, follow = [], []
        for t, x1 in rad['axis1']:
            if not t_prev <= t < t_wp:
                continue
            p = (x1, interp(rad['axis2'], t))
            dist = seg_distance(p, a, b)
            if k >= 2:
                dist = min(dist, seg_distance(p, corners[k - 2], a))
            path.append(dist)
            want = planned(t)
            follow.append(math.hypot(p[0] - want[0], p[1] - want[1]))
        fb = [math.hypot(*f.error.positions[:2]) for t, f in feedback if t_prev <= t < t_wp]
        waypoints.append({
            'k': k, 'time_s': times[k], 'length_rad': length, 'spread_s': spread,
            'missed_rad': missed,
            'late_s': late, 'late_vs_plan_s': late_plan,
            'path_max': max(path, default=float('nan')), 'path_rms': rms(path),
            'follow_max': max(follow, default=float('nan')), 'follow_rms': rms(follow),
            'fb_max': max(fb, default=float('nan')), 'samples': len(path)})
        path_all += path
        follow_all += follow
    return {'waypoints': waypoints, 'path_rms': rms(path_all), 'follow_rms': rms(follow_all)}


# ------------------------------------------------------------------------------------- a bus
class Bench:
    def __init__(self, spec: Spec, ros: RosClient, log_dir: pathlib.Path, tag: str):
        self.spec, self.ros, self.log_dir, self.tag = spec, ros, log_dir, tag
        self.procs: list[Proc] = []
        self.node_name = f'{spec.key}_node'

    def proc(self, args: list[str], name: str) -> Proc:
        p = Proc(args, self.log_dir, f'{self.tag}_{name}')
        self.procs.append(p)
        return p

    def close(self) -> None:
        for p in reversed(self.procs):       # the node first: it stops and disables the drives
            try:
                p.stop()
            except AssertionError as exc:
                print(f'   ({str(exc).splitlines()[0]})')


def run_vendor(spec: Spec, ros: RosClient, log_dir: pathlib.Path, n: int, sample_hz: float,
               band_frac: float, sync_period_s: float | None) -> dict:
    tag = spec.key + ('' if sync_period_s is None else f'_sync{sync_period_s:g}')
    params = load_params(f'{spec.key}.yaml', f'{spec.key}_node')
    rate_hz = float(params['publish_rate_hz'])
    convs, limits, joints = {}, {}, []
    start_stop = XplusMtDrive.start_stop_steps_s if spec.key == 'xplus_mt' else 0.0
    for d in DRIVES:
        p = params[f'drives.{d}']
        conv = UnitConversion(float(p['steps_per_rev']), float(p.get('gear_ratio', 1.0)),
                              p.get('unit', 'rad'), float(p.get('lead_m', 0.0)))
        convs[d] = conv
        lo, hi = sorted((conv.to_steps(p['min_position']), conv.to_steps(p['max_position'])))
        limits[d] = JointLimits(lo, hi, conv.to_steps(p['max_velocity']),
                                conv.to_steps(p['max_acceleration']), conv.steps_per_unit,
                                p.get('unit', 'rad'), start_stop)
        joints.append(p['joint_name'])
    b = Bench(spec, ros, log_dir, tag)
    link = str(free_port()) if spec.link != 'path' else str(log_dir / f'{tag}.tty')
    node_extra = [] if sync_period_s is None else ['-p', f'can.sync_period_s:={sync_period_s}']
    results: dict[str, Any] = {'vendor': spec.key, 'tag': tag, 'rate_hz': rate_hz,
                               'sync_period_s': sync_period_s, 'trajectories': []}
    true: dict[str, Recorder] = {}
    status: dict[str, Recorder] = {}
    try:
        if spec.link == 'broker':
            broker = b.proc([executable('stepper_sim', 'socketcand_broker'), '--port', link],
                            'broker')
            broker.wait_line('listening', 10)
        sim = b.proc([executable('stepper_sim', f'{spec.key}_sim'), '--ros-args',
                      '--params-file', str(CONFIG / f'{spec.key}_sim.yaml'),
                      '-p', f'{spec.link_param}:={link}', '-p', f'publish_rate_hz:={sample_hz}',
                      *[x for a in spec.sim_args for x in ('-p', a)]], 'sim')
        sim.wait_line('ready', 30)
        txn_s, txn_what = transaction_s(spec, link)
        results.update(transaction_s=txn_s, transaction_what=txn_what)
        node = b.proc([executable('stepper_drivers', b.node_name), '--ros-args',
                       '--params-file', str(CONFIG / f'{spec.key}.yaml'),
                       '-p', f'{spec.link_param}:={link}', *node_extra], 'node')
        for d in DRIVES:
            true[d] = Recorder(ros, Float64, f'/{spec.key}_sim/{d}/true_position_steps',
                               lambda m: m.data)
            status[d] = Recorder(ros, DriveStatus, f'/{b.node_name}/{d}/status')
        for d in DRIVES:
            wait_for(running(node, lambda d=d: (status[d].last_before(time.monotonic())
                                                or DriveStatus()).connected),
                     60, f'{spec.title} {d} connected')
            r = ros.call(SetBool, f'/{b.node_name}/{d}/enable', SetBool.Request(data=True), 30)
            if not r.success:
                raise RuntimeError(f'{d}: enable refused: {r.message}')
        for d in DRIVES:
            wait_for(running(node, lambda d=d: (status[d].last_before(time.monotonic())
                                                or DriveStatus()).enabled),
                     10, f'{spec.title} {d} enabled')
        wait_for(lambda: all(true[d].last_before(time.monotonic()) is not None
                             for d in DRIVES), 10, 'true positions')
        for i in range(n):
            shape = SHAPES[i % len(SHAPES)]
            points = [(t * spec.time_scale, x1, x2) for t, x1, x2 in shape]
            time.sleep(0.3)                   # standstill before it: a clean start position
            now = time.monotonic()
            start_steps = {d: true[d].last_before(now) for d in DRIVES}
            traj = build(joints, [p[0] for p in points],
                         [[convs[d].to_steps(x) for d, x in zip(DRIVES, p[1:])]
                          for p in points], joints)
            try:               # the node's own check, here: nothing is sent that it refuses
                plan(traj, {j: start_steps[d] for j, d in zip(joints, DRIVES)},
                     {j: limits[d] for j, d in zip(joints, DRIVES)})
            except TrajectoryError as exc:
                raise RuntimeError(f'trajectory {i + 1} is outside the limits: {exc}') from None
            msg = JointTrajectory(joint_names=joints)
            stamp_s = time.time() + LEAD_S
            start_t = time.monotonic() + LEAD_S
            msg.header.stamp = Time(sec=int(stamp_s), nanosec=int((stamp_s % 1) * 1e9))
            for t, x1, x2 in points:
                msg.points.append(JointTrajectoryPoint(positions=[x1, x2], time_from_start=(
                    Duration(sec=int(t), nanosec=int(round((t - int(t)) * 1e9))))))
            feedback: list = []
            result = send_goal(ros, b.node_name, FollowJointTrajectory.Goal(trajectory=msg),
                               lambda f: feedback.append((time.monotonic(), f)),
                               points[-1][0] + LEAD_S + 20.0)
            end_t = time.monotonic()
            time.sleep(0.2)
            raw = {d: true[d].between(start_t - 0.2, end_t) for d in DRIVES}
            samples = {d: on_time(raw[d], 1.0 / sample_hz) for d in DRIVES}
            dropped = sum(len(raw[d]) - len(samples[d]) for d in DRIVES)
            modes = sorted({m.mode for d in DRIVES for _t, m in status[d].between(start_t,
                                                                                  end_t)
                            if m.mode})
            res = analyse(points, start_t, start_steps, convs, limits, joints, samples,
                          feedback, band_frac)
            res.update(points=points, start_rad={d: convs[d].from_steps(start_steps[d])
                                                 for d in DRIVES},
                       error_code=result.error_code, error_string=result.error_string,
                       modes=modes, feedback_n=len(feedback), duration_s=end_t - start_t,
                       samples_n=sum(len(raw[d]) for d in DRIVES), samples_dropped=dropped,
                       samples={d: [(round(t - start_t, 4), convs[d].from_steps(x))
                                    for t, x in samples[d]] for d in DRIVES},
                       feedback=[(round(t - start_t, 4), list(f.desired.positions),
                                  list(f.actual.positions)) for t, f in feedback])
            results['trajectories'].append(res)
        for d in DRIVES:
            ros.call(SetBool, f'/{b.node_name}/{d}/enable', SetBool.Request(data=False), 30)
        results['load'] = os.getloadavg()[0]
        results['cores'] = os.cpu_count()
    finally:
        b.close()
        for rec in [*true.values(), *status.values()]:
            ros.in_spin(ros.node.destroy_subscription, rec.sub)
    node_log = (log_dir / f'{tag}_node.log').read_text(errors='replace')
    results['node_log_mode'] = [line.strip() for line in node_log.splitlines()
                                if 'interpolat' in line.lower()][:5]
    results['goal_spread_s'] = 1.0 / rate_hz + results['transaction_s']
    report(spec, results)
    return results


def fmt_ms(x: float | None) -> str:
    return '   -  ' if x is None else f'{1000 * x:+6.1f}'


def report(spec: Spec, r: dict) -> None:
    title = spec.title + ('' if r['sync_period_s'] is None
                          else f', can.sync_period_s {r["sync_period_s"]:g}')
    print(f'\n== {title} [{r["cores"]} cores, load {r["load"]:.2f}]')
    print(f'   {spec.line}; node at {r["rate_hz"]:g} Hz (poll period '
          f'{1000 / r["rate_hz"]:.1f} ms); one line transaction {1000 * r["transaction_s"]:.2f}'
          f' ms ({r["transaction_what"]})')
    modes = sorted({m for t in r['trajectories'] for m in t['modes']})
    print(f'   drive mode while following (DriveStatus.mode): {", ".join(modes) or "?"}'
          + (f'; node log: {r["node_log_mode"]}' if r['node_log_mode'] else ''))
    print('   traj wp  time   len | spread | late vs waypoint  | late vs plan      | path err '
          'max / rms      | follow err max / rms    | feedback max')
    print('                   rad |   ms   |  axis1    axis2 ms|  axis1    axis2 ms| mrad (% of '
          'length)        | mrad (% of length)      | mrad')
    spreads, worst_follow, worst_path = [], 0.0, 0.0
    for i, t in enumerate(r['trajectories']):
        for w in t['waypoints']:
            L = w['length_rad']
            if w['spread_s'] is not None:
                spreads.append(w['spread_s'])
            worst_follow = max(worst_follow, w['follow_max'] / L)
            worst_path = max(worst_path, w['path_max'] / L)
            print(f'   {i + 1:4} {w["k"]:2} {w["time_s"]:5.1f} {L:5.2f} | '
                  f'{fmt_ms(w["spread_s"])} | '
                  + ' '.join(fmt_ms(w['late_s'].get(d)) for d in DRIVES) + '   | '
                  + ' '.join(fmt_ms(w['late_vs_plan_s'].get(d)) for d in DRIVES) + '   | '
                  f'{1000 * w["path_max"]:6.1f} ({100 * w["path_max"] / L:4.2f} %) / '
                  f'{1000 * w["path_rms"]:5.1f} | '
                  f'{1000 * w["follow_max"]:6.1f} ({100 * w["follow_max"] / L:4.2f} %) / '
                  f'{1000 * w["follow_rms"]:5.1f} | {1000 * w["fb_max"]:6.1f}')
            for d, x in w['missed_rad'].items():
                print(f'           {d} never came within the band of this waypoint (the next '
                      f'move came first): closest {1000 * x:.1f} mrad')
        if t['error_code'] != 0:
            print(f'        result {t["error_code"]}: {t["error_string"]}')
    goal = r['goal_spread_s']
    worst = max(spreads) if spreads else None
    r['spread_max_s'], r['follow_worst_frac'], r['path_worst_frac'] = \
        worst, worst_follow, worst_path
    failed = [t['error_string'] for t in r['trajectories'] if t['error_code'] != 0]
    waypoints = sum(len(t['waypoints']) for t in r['trajectories'])
    missed = waypoints - len(spreads)
    r['waypoints'], r['waypoints_missed'] = waypoints, missed
    met = worst is not None and worst < goal and not missed
    print(f'   spread: max {fmt_ms(worst)} ms, median '
          f'{fmt_ms(statistics.median(spreads) if spreads else None)} ms over the {len(spreads)} '
          f'of {waypoints} waypoints that both axes reached; goal < {1000 * goal:.1f} ms (poll '
          f'period + one transaction) at every waypoint: {"met" if met else "NOT met"}'
          + (f' ({missed} waypoint(s) not reached by an axis)' if missed else ''))
    print(f'   path error max {100 * worst_path:.2f} % of the segment length; following error '
          f'max {100 * worst_follow:.2f} %'
          + (f'; goal < {100 * VECTOR_GOAL:g} %: '
             f'{"met" if worst_follow < VECTOR_GOAL else "NOT met"}'
             if spec.key == 'vector_step' else ''))
    n = sum(t['samples_n'] for t in r['trajectories'])
    dropped = sum(t['samples_dropped'] for t in r['trajectories'])
    print(f'   {len(r["trajectories"]) - len(failed)} of {len(r["trajectories"])} trajectories '
          'succeeded' + (f'; failed: {failed}' if failed else '')
          + f'; {dropped} of {n} true-position samples left out (late: a burst after a stall)')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', nargs='+', choices=list(VENDORS), default=list(VENDORS))
    ap.add_argument('--trajectories', type=int, default=3, help='per vendor (default 3)')
    ap.add_argument('--sample-rate', type=float, default=200.0,
                    help="the simulators' true-position rate [Hz] (default 200)")
    ap.add_argument('--band', type=float, default=0.005,
                    help='arrival band, fraction of the axis\'s segment distance (default 0.005)')
    ap.add_argument('--vector-sync-period', type=float, nargs='*', default=[0.01],
                    help='Vector Step also with can.sync_period_s = each of these [s] '
                         '(interpolated position; default 0.01; none: only config/)')
    ap.add_argument('--json', type=pathlib.Path, help='write every figure to this file')
    args = ap.parse_args()
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_traj_'))
    domain_lock = reserve_domain()      # noqa: F841 - held until the end of the run
    print(f'trajectory benchmark: {machine()}; ROS_DOMAIN_ID '
          f'{os.environ.get("ROS_DOMAIN_ID", "0")}; true positions at {args.sample_rate:g} Hz; '
          f'arrival band {100 * args.band:g} % of the segment distance (>= 1 step); logs '
          f'{log_dir}')
    jobs = []
    for key in args.vendor:
        jobs.append((key, None))
        if key == 'vector_step':
            jobs += [(key, s) for s in args.vector_sync_period]
    results: dict[str, Any] = {'machine': machine(), 'runs': []}
    failed = 0
    ros = RosClient('bench_trajectory')
    try:
        for key, sync in jobs:
            try:
                results['runs'].append(run_vendor(VENDORS[key], ros, log_dir, args.trajectories,
                                                  args.sample_rate, args.band, sync))
            except Exception as exc:  # noqa: BLE001 - report, go on with the next one
                failed += 1
                print(f'\n== {key}{"" if sync is None else f" sync {sync:g}"}: FAILED: {exc} '
                      f'(logs in {log_dir})', flush=True)
                results['runs'].append({'vendor': key, 'sync_period_s': sync,
                                        'error': str(exc)})
            sys.stdout.flush()
    finally:
        ros.close()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
