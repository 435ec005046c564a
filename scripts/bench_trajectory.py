#!/usr/bin/env python3
"""Trajectory benchmark: arrival spread at the waypoints and path error, per bus.

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

MoveIt-like dense trajectories (`--dense`), per bus with its config/<vendor>.yaml (Vector Step:
its SYNC of 0.1 s, profile position; `--vector-sync-period S` adds runs with that period):
a straight line in the joint space of the first two joints (2.0 and 1.0 rad, 2.24 rad long)
and a quarter circle of radius 1 rad (1.57 rad long), each with quintic timing, rest to rest,
over 3 s, a point every 0.1 s and every 0.05 s (`--dt`), with positions, velocities and
accelerations as MoveIt's time parameterisation fills them, the first point the start state at
time 0 (as MoveIt sends it), header.stamp zero (start when the goal arrives) and no tolerances.
Per trajectory:

- finish time: goal sent -> result arrived, against the duration and MoveIt's limit (its example
  configurations: duration x 1.2 + 0.5 s); the result code and text;
- geometric path error: the distance in the (joint1, joint2) plane of each true-position sample
  (goal sent .. result) from the polyline of the trajectory's points (the start included), max
  and RMS, rad and % of the polyline's length;
- timing error: per joint, the true position against the trajectory's own positions
  interpolated linearly at the same time (time 0: the goal sent), max;
- the node's merge of the points into segments (its log line for the goal);
- stall share per joint: the share of the middle 80 % of the move (trajectory time 0.1 .. 0.9 x
  duration) in which the joint runs below a quarter of its planned speed (the points'
  velocities, linear between them); its speed from the true positions, the difference over
  STALL_WINDOW_S around each sample; in brackets the same share counted only where the plan
  moves the joint at least one step in STALL_WINDOW_S (slower, an axis that steps exactly as
  planned reads 0 in most windows: a stepper cannot move less than a step, and the true
  positions are whole steps); timing error also in % of the joint's travel; finish
  against MoveIt's built-in limit, 1.1 x duration + 0.5 s, beside its example configurations'.
  Goals (X-PLUS MT, Vector Step, RD4): stall <= 5 %, timing error <= 2 % of the travel.

Two nodes (`--two-node`): an X-PLUS MT node and an RD4 node (line timing on), each sent its two
joints' part of one four-joint trajectory (the quintic line, 2.0 and 1.0 rad per node, 3.2 s)
with the same header.stamp, 0.8 s ahead, as MoveIt splits a planning group over two
controllers; points every 0.8 s and every 0.1 s (`--two-node-dt`). Per node the finish time
(from the stamp, where MoveIt counts from for a stamped trajectory), result, path error in its
joints' plane; per joint the timing error (time 0: the stamp); and the arrival spread at each
point: the time each axis passes the point's whole-step position (linear between the two
true-position samples around it; an axis whose point is its start step is left out), max - min
over the four axes, against one poll period of each node plus one RD4 line transaction.

Run: source scripts/env.sh && python scripts/bench_trajectory.py [--vendor rd4 ...]
     [--trajectories N] [--sample-rate HZ] [--band F] [--vector-sync-period [S ...]]
     [--dense] [--two-node] [--dt S ...] [--two-node-dt S ...]
     [--json out.json]            (everything but the dense part: about 100 s)
     [--from-json out.json]       (only the dense tables again, from a --json file of a run)
     --dense and/or --two-node run only those parts (all four buses and both: a few minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import re
import statistics
import sys
import tempfile
import threading
import time
from typing import Any

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from bench_command_path import bare_rate, load_params, machine, reserve_domain, running
from builtin_interfaces.msg import Duration, Time
from control_msgs.action import FollowJointTrajectory
from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers.contract.units import UnitConversion
from stepper_drivers.motion.trajectory import JointLimits, TrajectoryError, build, plan

# the one trapezoid formula of the node (follow.Run.desired_steps uses it); Run itself needs
# the node's live axes
from stepper_drivers.motion.trajectory import along as _along
from stepper_drivers.vendors.xplus_mt import XplusMtDrive
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.harness import CONFIG, Proc, executable, free_port, wait_for
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

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

# MoveIt-like dense trajectories (--dense, --two-node)
MOVEIT_SCALING = 1.2           # allowed_execution_duration_scaling (its example configurations)
MOVEIT_MARGIN_S = 0.5          # allowed_goal_duration_margin
MOVEIT_BUILTIN_SCALING = 1.1   # MoveIt's own default of allowed_execution_duration_scaling
STALL_FRACTION = 0.25          # a joint below this share of its planned speed stalls
STALL_WINDOW_S = 0.04          # speed: the difference of the true positions over this window
STALL_MIDDLE = (0.1, 0.9)      # of the duration: the middle 80 % of the move
DENSE_DURATION_S = 3.0
# --node-param: extra parameters for the nodes of the dense runs
NODE_PARAMS: list[str] = []
DENSE_KINDS = ('line', 'arc')
LINE_RAD = (2.0, 1.0)          # per joint: 2.24 rad in joint space
ARC_RADIUS_RAD = 1.0           # a quarter circle: 1.57 rad
TWO_NODE_LEAD_S = 0.8          # header.stamp this far ahead, the same for both parts
TWO_NODE_DURATION_S = 3.2      # a point every 0.8 s falls on the 0.1 s points too
TWO_NODE = ('xplus_mt', 'rd4')


def duration_msg(t: float) -> Duration:
    sec = int(math.floor(t))
    nanosec = int(round((t - sec) * 1e9))
    return Duration(sec=sec + nanosec // 1_000_000_000, nanosec=nanosec % 1_000_000_000)


def quintic(s: float) -> tuple[float, float, float]:
    """Rest-to-rest quintic timing: f(s), df/ds, d2f/ds2 for s in 0..1."""
    return (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5, 30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4,
            60 * s - 180 * s ** 2 + 120 * s ** 3)


def line_points(start: list[float], delta: list[float], duration_s: float, dt_s: float
                ) -> list[tuple[float, list[float], list[float], list[float]]]:
    """[(time_from_start, positions, velocities, accelerations)]: a straight line from `start`
    by `delta` with quintic timing, a point every dt_s, the first the start state at time 0."""
    n, T = int(round(duration_s / dt_s)), duration_s
    out = []
    for k in range(n + 1):
        f, df, ddf = quintic(k / n)
        out.append((round(k * dt_s, 9), [a + f * d for a, d in zip(start, delta)],
                    [df / T * d for d in delta], [ddf / T ** 2 * d for d in delta]))
    return out


def arc_points(start: list[float], signs: tuple[float, float], radius: float,
               duration_s: float, dt_s: float
               ) -> list[tuple[float, list[float], list[float], list[float]]]:
    """A quarter circle from `start`: joint1 = x1 + sx r sin(phi), joint2 = x2 + sy r (1 -
    cos(phi)), phi 0..pi/2 with quintic timing (each joint moves one way only)."""
    n, T = int(round(duration_s / dt_s)), duration_s
    (x1, x2), (sx, sy), r = start, signs, radius
    out = []
    for k in range(n + 1):
        f, df, ddf = quintic(k / n)
        phi, w, dw = math.pi / 2 * f, math.pi / 2 * df / T, math.pi / 2 * ddf / T ** 2
        out.append((round(k * dt_s, 9),
                    [x1 + sx * r * math.sin(phi), x2 + sy * r * (1 - math.cos(phi))],
                    [sx * r * math.cos(phi) * w, sy * r * math.sin(phi) * w],
                    [sx * r * (math.cos(phi) * dw - math.sin(phi) * w * w),
                     sy * r * (math.sin(phi) * dw + math.cos(phi) * w * w)]))
    return out


def away(start: list[float]) -> tuple[float, float]:
    """Directions that keep the joints near where they began: + below 1.0 / 0.5 rad, else -."""
    return (1.0 if start[0] < 1.0 else -1.0), (1.0 if start[1] < 0.5 else -1.0)


def trajectory_msg(joints: list[str], points, columns=None) -> JointTrajectory:
    """The points as MoveIt sends them (header.stamp zero); `columns`: these joints' part."""
    idx = list(range(len(joints))) if columns is None else columns
    msg = JointTrajectory(joint_names=[joints[i] for i in idx])
    for t, pos, vel, acc in points:
        msg.points.append(JointTrajectoryPoint(
            positions=[float(pos[i]) for i in idx], velocities=[float(vel[i]) for i in idx],
            accelerations=[float(acc[i]) for i in idx], time_from_start=duration_msg(t)))
    return msg


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


class ActionGoal:
    """One follow_joint_trajectory goal (rclpy ActionClient through ros.in_spin: see
    RosClient.in_spin). The server is found when it is made; sent_t is taken just before the
    goal goes out, accepted_t and result_t when the answers arrive (CLOCK_MONOTONIC, in the
    spin thread)."""

    def __init__(self, ros: RosClient, node: str):
        from rclpy.action import ActionClient
        self.ros, self.name = ros, f'/{node}/follow_joint_trajectory'
        self.client = ActionClient(ros.node, FollowJointTrajectory, self.name)
        self.sent_t = self.accepted_t = self.result_t = None
        self._result_fut = None
        if not self.client.wait_for_server(timeout_sec=10):
            self.close()
            raise RuntimeError(f'{self.name} not available')

    def _wait(self, fut, t: float, what: str):
        done = threading.Event()
        fut.add_done_callback(lambda _f: done.set())
        if not done.wait(t):
            raise RuntimeError(f'no {what} from {self.name} in {t:g} s')
        return fut.result()

    def send(self, goal, on_feedback=lambda f: None) -> None:
        def accepted(_f):
            self.accepted_t = time.monotonic()
        def send_now():                  # in the spin thread: the goal goes out now
            self.sent_t = time.monotonic()
            return self.client.send_goal_async(
                goal, feedback_callback=lambda f: on_feedback(f.feedback))
        fut = self.ros.in_spin(send_now)
        fut.add_done_callback(accepted)
        handle = self._wait(fut, 10.0, 'goal response')
        if not handle.accepted:
            raise RuntimeError(f'goal not accepted by {self.name}')

        def arrived(_f):
            self.result_t = time.monotonic()
        self._result_fut = self.ros.in_spin(handle.get_result_async)
        self._result_fut.add_done_callback(arrived)

    def result(self, timeout_s: float):
        return self._wait(self._result_fut, timeout_s, 'result').result

    def close(self) -> None:
        self.ros.in_spin(self.client.destroy)


def send_goal(ros: RosClient, node: str, goal, on_feedback, timeout_s: float):
    """One follow_joint_trajectory goal; its result."""
    g = ActionGoal(ros, node)
    try:
        g.send(goal, on_feedback)
        return g.result(timeout_s)
    finally:
        g.close()


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



def enable_all(ros: RosClient, node: Proc, status: dict, node_path: str, drives, title: str
               ) -> None:
    """Wait until each drive's status says connected, enable it (its `enable` service), and
    wait until each says enabled; the node's death ends every wait (`running`). An enable
    whose reply was lost (the node then drops the link and connects again) is tried once more
    after the reconnect, with a line saying so: a simulator stalled right after it started (by
    stale Fast DDS segments in /dev/shm: docs/troubleshooting.md) is no figure of the bench."""
    def last(d):
        return status[d].last_before(time.monotonic()) or DriveStatus()
    for d in drives:
        wait_for(running(node, lambda d=d: last(d).connected), 60, f'{title} {d} connected')
        for attempt in (1, 2):
            seen = last(d).link_reconnects
            r = ros.call(SetBool, f'{node_path}/{d}/enable', SetBool.Request(data=True), 30)
            if r.success:
                break
            if attempt == 2 or 'no reply' not in r.message:
                raise RuntimeError(f'{d}: enable refused: {r.message}')
            print(f'   {title} {d}: the enable lost its reply ({r.message[-90:]}); once more '
                  'after the reconnect (stale Fast DDS segments in /dev/shm? '
                  'docs/troubleshooting.md)', flush=True)
            wait_for(running(node, lambda d=d, seen=seen: last(d).connected
                             and last(d).link_reconnects > seen), 30, f'{title} {d} reconnected')
    for d in drives:
        wait_for(running(node, lambda d=d: last(d).enabled), 10, f'{title} {d} enabled')

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


def polyline_figures(samples: dict[str, list[tuple[float, float]]], drives: tuple[str, str],
                     poly: list[tuple[float, float]], t_from: float, t_to: float) -> dict:
    """Geometric path error: each sample of the first drive in t_from..t_to with the second
    interpolated at its time (the simulator publishes both at one tick), its distance in the
    plane from the polyline `poly` [rad]; max, RMS, and in fractions of the polyline's length."""
    length = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(poly, poly[1:]))
    first, second = drives
    dist = []
    for t, x1 in samples[first]:
        if t_from <= t <= t_to:
            p = (x1, interp(samples[second], t))
            dist.append(min(seg_distance(p, a, b) for a, b in zip(poly, poly[1:])))
    worst, r = max(dist, default=float('nan')), rms(dist)
    return {'length_rad': length, 'path_max_rad': worst, 'path_rms_rad': r,
            'path_max_frac': worst / length, 'path_rms_frac': r / length,
            'path_samples': len(dist)}


def timing_error(samples: list[tuple[float, float]], own: list[tuple[float, float]], t0: float,
                 t_from: float, t_to: float) -> tuple[float, float | None]:
    """(max |true - the trajectory's own position linear between its points at the same time|
    [rad], trajectory time of that max) over the samples in t_from..t_to; own: [(time_from_start,
    position)], t0 the trajectory's start (held before and after its points)."""
    worst, at = float('nan'), None
    for t, x in samples:
        if t_from <= t <= t_to:
            err = abs(x - interp(own, t - t0))
            if not err <= worst:
                worst, at = err, t - t0
    return worst, at


def crossing(samples: list[tuple[float, float]], target: float, sign: float
             ) -> tuple[float, float] | None:
    """(when a joint moving one way (sign) first reached `target` (steps, a whole step): linear
    between the two samples around it, or the first sample within half a step when it stops
    short of the exact value; how far apart those two samples are); None when it never got
    there."""
    before = None
    for t, x in samples:
        if sign * (x - target) >= -0.5:
            if before is not None and sign * (x - target) >= 0 > sign * (before[1] - target):
                (t0, x0) = before
                return t0 + (t - t0) * (target - x0) / (x - x0), t - t0
            return t, (t - before[0]) if before is not None else 0.0
        before = (t, x)
    return None


def samples_lag(samples: list[tuple[float, float]], goal: float, tol: float,
                result_t: float) -> float | None:
    """A SUCCESSFUL result means the node saw the joint within a step of its goal: seconds from
    the result to the first sample there (> 0: the samples arrive here late, this process fell
    behind them and stamped them late); inf when no sample up to the end shows it there."""
    at = next((t for t, x in samples if abs(x - goal) <= tol), None)
    return math.inf if at is None else at - result_t


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


class Bus:
    """One bus brought up (`bring_up`): the simulator with its line timing on and its true
    positions at the sample rate, the line transaction measured on it before the node opened the
    link, the node with config/<vendor>.yaml, the first two drives enabled."""

    def __init__(self, spec: Spec, bench: Bench, params: dict):
        self.spec, self.bench = spec, bench
        self.rate_hz = float(params['publish_rate_hz'])
        self.convs: dict[str, UnitConversion] = {}
        self.limits: dict[str, JointLimits] = {}
        self.joints: list[str] = []
        start_stop = XplusMtDrive.start_stop_steps_s if spec.key == 'xplus_mt' else 0.0
        for d in DRIVES:
            p = params[f'drives.{d}']
            conv = UnitConversion(float(p['steps_per_rev']), float(p.get('gear_ratio', 1.0)),
                                  p.get('unit', 'rad'), float(p.get('lead_m', 0.0)))
            self.convs[d] = conv
            lo, hi = sorted((conv.to_steps(p['min_position']), conv.to_steps(p['max_position'])))
            self.limits[d] = JointLimits(lo, hi, conv.to_steps(p['max_velocity']),
                                         conv.to_steps(p['max_acceleration']),
                                         conv.steps_per_unit, p.get('unit', 'rad'), start_stop)
            self.joints.append(p['joint_name'])
        self.true: dict[str, Recorder] = {}
        self.status: dict[str, Recorder] = {}
        self.node: Proc | None = None
        self.transaction_s, self.transaction_what = float('nan'), ''

    def still(self, timeout_s: float = 10.0) -> None:
        """Both drives report standing still (status.moving false)."""
        for d in DRIVES:
            wait_for(running(self.node, lambda d=d: not (self.status[d].last_before(
                time.monotonic()) or DriveStatus(moving=True)).moving),
                timeout_s, f'{self.spec.title} {d} at rest')

    def true_rad(self, d: str, t: float) -> float:
        return self.convs[d].from_steps(self.true[d].last_before(t))

    def log_size(self) -> int:
        return self.node.log_path.stat().st_size

    def log_since(self, offset: int) -> list[str]:
        with open(self.node.log_path, 'rb') as f:
            f.seek(offset)
            return f.read().decode(errors='replace').splitlines()

    def disable(self, ros: RosClient) -> None:
        for d in DRIVES:
            ros.call(SetBool, f'/{self.bench.node_name}/{d}/enable', SetBool.Request(data=False),
                     30)

    def close(self, ros: RosClient) -> None:
        self.bench.close()
        for rec in [*self.true.values(), *self.status.values()]:
            ros.in_spin(ros.node.destroy_subscription, rec.sub)


def bring_up(spec: Spec, ros: RosClient, log_dir: pathlib.Path, tag: str, sample_hz: float,
             node_extra: list[str]) -> Bus:
    b = Bench(spec, ros, log_dir, tag)
    bus = Bus(spec, b, load_params(f'{spec.key}.yaml', f'{spec.key}_node'))
    link = str(free_port()) if spec.link != 'path' else str(log_dir / f'{tag}.tty')
    true, status = bus.true, bus.status
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
        bus.transaction_s, bus.transaction_what = transaction_s(spec, link)
        node = bus.node = b.proc([executable('stepper_drivers', b.node_name), '--ros-args',
                                  '--params-file', str(CONFIG / f'{spec.key}.yaml'),
                                  '-p', f'{spec.link_param}:={link}', *node_extra], 'node')
        for d in DRIVES:
            true[d] = Recorder(ros, Float64, f'/{spec.key}_sim/{d}/true_position_steps',
                               lambda m: m.data)
            status[d] = Recorder(ros, DriveStatus, f'/{b.node_name}/{d}/status')
        enable_all(ros, node, status, f'/{b.node_name}', DRIVES, spec.title)
        wait_for(lambda: all(true[d].last_before(time.monotonic()) is not None
                             for d in DRIVES), 10, 'true positions')
    except BaseException:
        bus.close(ros)
        raise
    return bus


def run_vendor(spec: Spec, ros: RosClient, log_dir: pathlib.Path, n: int, sample_hz: float,
               band_frac: float, sync_period_s: float | None) -> dict:
    tag = spec.key + ('' if sync_period_s is None else f'_sync{sync_period_s:g}')
    node_extra = [] if sync_period_s is None else ['-p', f'can.sync_period_s:={sync_period_s}']
    bus = bring_up(spec, ros, log_dir, tag, sample_hz, node_extra)
    b, rate_hz, convs, limits, joints = bus.bench, bus.rate_hz, bus.convs, bus.limits, bus.joints
    true, status = bus.true, bus.status
    results: dict[str, Any] = {'vendor': spec.key, 'tag': tag, 'rate_hz': rate_hz,
                               'sync_period_s': sync_period_s, 'trajectories': [],
                               'transaction_s': bus.transaction_s,
                               'transaction_what': bus.transaction_what}
    try:
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
                               lambda f, feedback=feedback: feedback.append((time.monotonic(), f)),
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
        bus.disable(ros)
        results['load'] = os.getloadavg()[0]
        results['cores'] = os.cpu_count()
    finally:
        bus.close(ros)
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


# ------------------------------------------------------------------ MoveIt-like dense trajectories
def moveit_limit_s(duration_s: float) -> float:
    return MOVEIT_SCALING * duration_s + MOVEIT_MARGIN_S


def builtin_limit_s(duration_s: float) -> float:
    return MOVEIT_BUILTIN_SCALING * duration_s + MOVEIT_MARGIN_S


def dense_points(kind: str, start: list[float], dt: float):
    """The points of one dense trajectory from where it started (as run_dense makes them)."""
    signs = away(start)
    return (line_points(start, [s * x for s, x in zip(signs, LINE_RAD)], DENSE_DURATION_S, dt)
            if kind == 'line' else arc_points(start, signs, ARC_RADIUS_RAD, DENSE_DURATION_S,
                                              dt))


def stall_figures(samples: dict[str, list[tuple[float, float]]], points,
                  step_rad: dict[str, float] | None = None) -> dict:
    """Per drive: stall share (the module's docstring), with step_rad (drive -> rad per step)
    also the share where the plan moves a step per STALL_WINDOW_S, and timing error in % of
    its travel. samples: drive -> [(time since the goal was sent, rad)]."""
    out: dict[str, dict] = {'stall_share': {}, 'travel_rad': {}}
    if step_rad:
        out['stall_share_resolvable'] = {}
    duration = points[-1][0]
    lo, hi = (f * duration for f in STALL_MIDDLE)
    for i, d in enumerate(DRIVES):
        planned = [(p[0], abs(p[2][i])) for p in points]
        xs = samples[d]
        below = total = below_resolvable = resolvable = 0
        for t, _x in xs:
            if not lo <= t <= hi:
                continue
            before = [(ts, x) for ts, x in xs if t - STALL_WINDOW_S / 2 - 1e-9 <= ts <= t]
            after = [(ts, x) for ts, x in xs if t <= ts <= t + STALL_WINDOW_S / 2 + 1e-9]
            (t0, x0), (t1, x1) = before[0], after[-1]
            if t1 - t0 < STALL_WINDOW_S / 2:
                continue
            speed, plan = abs(x1 - x0) / (t1 - t0), interp(planned, t)
            total += 1
            below += speed < STALL_FRACTION * plan
            if step_rad and plan * STALL_WINDOW_S >= step_rad[d]:
                resolvable += 1
                below_resolvable += speed < STALL_FRACTION * plan
        out['stall_share'][d] = below / total if total else float('nan')
        if step_rad:
            out['stall_share_resolvable'][d] = (below_resolvable / resolvable if resolvable
                                                else float('nan'))
        out['travel_rad'][d] = abs(points[-1][1][i] - points[0][1][i])
    return out


def merge_line(lines: list[str]) -> dict:
    """The node's log line on merging points into segments for one goal, parsed; its warnings
    about the goal (refusal, outcome)."""
    out: dict[str, Any] = {'merge': None, 'segments': None, 'min_segment_s': None,
                           'warnings': [ln.strip() for ln in lines if 'WARN' in ln
                                        or 'ERROR' in ln][:5]}
    for ln in lines:
        m = re.search(r'(\d+) points followed as (\d+) segments of at least ([0-9.e+-]+) s', ln)
        chain = re.search(r'(\d+) points followed as one chain of (\d+) runs', ln)
        if m:
            out.update(merge=ln.strip(), points=int(m.group(1)), segments=int(m.group(2)),
                       min_segment_s=float(m.group(3)))
        elif chain:
            out.update(merge=ln.strip(), points=int(chain.group(1)), chain_runs=int(
                chain.group(2)))
        if m or chain:
            far = re.search(r'within (.*)$', ln)
            out['merge_far'] = far.group(1).strip() if far else ''
    return out


def collect(rec: Recorder, t0: float, t1: float, period_s: float) -> tuple[list, int]:
    """(the on-time samples of t0 - 0.2 .. t1 + 0.2, how many were left out)."""
    raw = rec.between(t0 - 0.2, t1 + 0.2)
    kept = on_time(raw, period_s)
    return kept, len(raw) - len(kept)


def run_dense(spec: Spec, ros: RosClient, log_dir: pathlib.Path, sample_hz: float,
              kinds: list[str], steps_s: list[float], sync_period_s: float | None) -> dict:
    """The MoveIt-like dense trajectories on one bus (see the module's docstring)."""
    tag = f'{spec.key}_dense' + ('' if sync_period_s is None else f'_sync{sync_period_s:g}')
    node_extra = [] if sync_period_s is None else ['-p', f'can.sync_period_s:={sync_period_s}']
    node_extra += [x for a in NODE_PARAMS for x in ('-p', a)]
    results: dict[str, Any] = {'part': 'dense', 'vendor': spec.key, 'tag': tag,
                               'sync_period_s': sync_period_s, 'trajectories': []}
    bus = bring_up(spec, ros, log_dir, tag, sample_hz, node_extra)
    results.update(rate_hz=bus.rate_hz, transaction_s=bus.transaction_s,
                   transaction_what=bus.transaction_what, joints=bus.joints)
    try:
        for kind in kinds:
            for dt in steps_s:
                res: dict[str, Any] = {'kind': kind, 'dt_s': dt, 'duration_s': DENSE_DURATION_S,
                                       'limit_s': moveit_limit_s(DENSE_DURATION_S)}
                results['trajectories'].append(res)
                try:
                    bus.still()
                    time.sleep(0.3)                  # standstill: a clean start position
                    start = [bus.true_rad(d, time.monotonic()) for d in DRIVES]
                    signs = away(start)
                    points = (line_points(start, [s * x for s, x in zip(signs, LINE_RAD)],
                                          DENSE_DURATION_S, dt) if kind == 'line' else
                              arc_points(start, signs, ARC_RADIUS_RAD, DENSE_DURATION_S, dt))
                    res.update(_dense_one(bus, ros, points, sample_hz))
                except Exception as exc:  # noqa: BLE001 - the rest of this bus is doubtful
                    res['error'] = f'{type(exc).__name__}: {exc}'
                    results['error'] = f'{kind} {dt:g} s: {res["error"]}'
                    break
            if 'error' in results:
                break
        if 'error' not in results:
            bus.disable(ros)
        results['load'] = os.getloadavg()[0]
        results['cores'] = os.cpu_count()
    finally:
        bus.close(ros)
    report_dense(spec, results, log_dir)
    return results


def _dense_one(bus: Bus, ros: RosClient, points, sample_hz: float) -> dict:
    """Send one trajectory (header.stamp zero) and measure it."""
    feedback: list = []
    mark = bus.log_size()
    g = ActionGoal(ros, bus.bench.node_name)
    try:
        g.send(FollowJointTrajectory.Goal(trajectory=trajectory_msg(bus.joints, points)),
               lambda f: feedback.append((time.monotonic(), f)))
        try:
            result = g.result(moveit_limit_s(points[-1][0]) + 20.0)
        except RuntimeError:
            raise RuntimeError(
                f'no result {time.monotonic() - g.sent_t:.1f} s after the goal was sent '
                f'(MoveIt would have canceled at {moveit_limit_s(points[-1][0]):.1f} s); last '
                f'feedback: {_last_feedback(feedback, g.sent_t)}') from None
    finally:
        g.close()
    time.sleep(0.3)                              # the last samples and log lines are in
    t0, t1 = g.sent_t, g.result_t
    samples, dropped = {}, 0
    for d in DRIVES:
        kept, left = collect(bus.true[d], t0, t1, 1.0 / sample_hz)
        samples[d] = [(t, bus.convs[d].from_steps(x)) for t, x in kept]
        dropped += left
    poly = [(p[1][0], p[1][1]) for p in points]
    out = polyline_figures(samples, DRIVES, poly, t0, t1)
    out['timing_max_rad'], out['timing_at_s'] = {}, {}
    for i, d in enumerate(DRIVES):
        own = [(p[0], p[1][i]) for p in points]
        worst, at = timing_error(samples[d], own, t0, t0, t1)
        out['timing_max_rad'][d], out['timing_at_s'][d] = worst, at
    fb = {d: max((abs(f.error.positions[i]) for _t, f in feedback), default=float('nan'))
          for i, d in enumerate(DRIVES)}
    if result.error_code == 0:
        out['samples_lag_s'] = max(samples_lag(
            samples[d], points[-1][1][i], 1.5 / bus.convs[d].steps_per_unit, t1)
            for i, d in enumerate(DRIVES))
    out['step_rad'] = {d: 1.0 / bus.convs[d].steps_per_unit for d in DRIVES}
    out.update(stall_figures({d: [(t - t0, x) for t, x in samples[d]] for d in DRIVES}, points,
                             out['step_rad']))
    out.update(merge_line(bus.log_since(mark)))
    out.update(points_n=len(points), error_code=result.error_code,
               error_string=result.error_string, finish_s=t1 - t0,
               accepted_s=(g.accepted_t - t0) if g.accepted_t else None,
               start_rad=list(points[0][1]), end_rad=list(points[-1][1]),
               feedback_n=len(feedback), feedback_error_max_rad=fb, samples_dropped=dropped,
               samples={d: [(round(t - t0, 4), x) for t, x in samples[d]] for d in DRIVES})
    return out


def _last_feedback(feedback: list, t0: float) -> str:
    if not feedback:
        return 'none'
    t, f = feedback[-1]
    return (f'at {t - t0:.2f} s desired {[round(x, 3) for x in f.desired.positions]} actual '
            f'{[round(x, 3) for x in f.actual.positions]} rad')


def code_name(code: int) -> str:
    names = {0: 'SUCCESSFUL', -1: 'INVALID_GOAL', -2: 'INVALID_JOINTS',
             -3: 'OLD_HEADER_TIMESTAMP', -4: 'PATH_TOLERANCE_VIOLATED',
             -5: 'GOAL_TOLERANCE_VIOLATED'}
    return names.get(code, str(code))


def dense_row(title: str, t: dict) -> str:
    """One trajectory as a markdown table row."""
    what = f'{t["kind"]}, {t["dt_s"]:g} s'
    if 'finish_s' not in t:
        return f'| {title} | {what} | **failed**: {t.get("error", "?")} | | | | |'
    result = code_name(t['error_code'])
    if t['error_code'] != 0:
        result = f'**{result}**: {t["error_string"]}'
    finish = t['finish_s']
    verdict = 'within' if finish <= t['limit_s'] else '**over**'
    if t.get('samples_lag_s', 0) > 0:
        result += f' (samples late by {t["samples_lag_s"]:.2f} s: figures **not valid**)'
    timing = ' / '.join(f'{1000 * t["timing_max_rad"][d]:.1f}' for d in DRIVES)
    if 'travel_rad' in t:
        timing += ' (' + ' / '.join(f'{100 * t["timing_max_rad"][d] / t["travel_rad"][d]:.1f}'
                                    for d in DRIVES) + ' % of travel)'
    stall = ' / '.join(f'{100 * t["stall_share"][d]:.0f} %' for d in DRIVES) \
        if 'stall_share' in t else '-'
    if 'stall_share_resolvable' in t:
        stall += ' (' + ' / '.join(f'{100 * t["stall_share_resolvable"][d]:.0f} %'
                                   for d in DRIVES) + ')'
    builtin = builtin_limit_s(t['duration_s'])
    verdict += f' {t["limit_s"]:.1f}; {"within" if finish <= builtin else "**over**"}'
    verdict += f' {builtin:.1f}'
    segs = ('no merge' if t.get('segments') is None and t.get('chain_runs') is None else
            f'{t["points"]} points as one chain of {t["chain_runs"]} runs per joint; '
            f'plan within {t.get("merge_far", "?")} of the points' if t.get('segments') is None
            else f'{t["points"]} points as {t["segments"]} segments (>= '
            f'{t["min_segment_s"]:.3g} s); plan within {t.get("merge_far", "?")} of the points')
    return (f'| {title} | {what} ({t["points_n"]} points) | {result} | {finish:.2f} s ({verdict}'
            f') | {stall} | {1000 * t["path_max_rad"]:.1f} / '
            f'{1000 * t["path_rms_rad"]:.1f} mrad ({100 * t["path_max_frac"]:.2f} / '
            f'{100 * t["path_rms_frac"]:.2f} %) | '
            f'{timing} | {segs} |')


DENSE_HEADER = ('| bus | trajectory | result | finish (MoveIt limit x 1.2; x 1.1) | stall joint1 '
                '/ joint2 (where the plan moves a step per window) | path error max / RMS (% '
                "of length) | timing error max joint1 / joint2 (mrad) | node's segments |\n"
                '|---|---|---|---|---|---|---|---|')


def report_dense(spec: Spec, r: dict, log_dir: pathlib.Path) -> None:
    title = spec.title + ('' if r['sync_period_s'] is None
                          else f', can.sync_period_s {r["sync_period_s"]:g}')
    print(f'\n== {title}: MoveIt-like dense trajectories [{r.get("cores")} cores, load '
          f'{r.get("load", float("nan")):.2f}]')
    print(f'   {spec.line}; node at {r["rate_hz"]:g} Hz; one line transaction '
          f'{1000 * r["transaction_s"]:.2f} ms; {DENSE_DURATION_S:g} s quintic, MoveIt limit '
          f'{moveit_limit_s(DENSE_DURATION_S):.1f} s; header.stamp 0; no tolerances')
    print(DENSE_HEADER)
    for t in r['trajectories']:
        print(dense_row(spec.title, t))
    _dense_notes(r, log_dir)


def _dense_notes(r: dict, log_dir: pathlib.Path | None) -> None:
    for t in r['trajectories']:
        extra = []
        if t.get('accepted_s') is not None:
            extra.append(f'accepted {1000 * t["accepted_s"]:.1f} ms after sent')
        if 'feedback_error_max_rad' in t:
            extra.append('feedback |error| max ' + ' / '.join(
                f'{1000 * t["feedback_error_max_rad"][d]:.1f}' for d in DRIVES) + ' mrad')
        if 'timing_at_s' in t:
            extra.append('timing max at ' + ' / '.join(
                '-' if t['timing_at_s'][d] is None else f'{t["timing_at_s"][d]:.2f}'
                for d in DRIVES) + ' s')
        if t.get('samples_dropped'):
            extra.append(f'{t["samples_dropped"]} samples left out (late)')
        if t.get('samples_lag_s', 0) > 0:
            extra.append(f'NOT VALID: the samples show a joint at its goal '
                         f'{t["samples_lag_s"]:.2f} s after the result (this process fell '
                         'behind the samples)')
        for w in t.get('warnings', []):
            extra.append(f'node: {w[-200:]}')
        if extra:
            print(f'   {t["kind"]} {t["dt_s"]:g} s: ' + '; '.join(extra))
    if 'error' in r and log_dir is not None:
        print(f'   FAILED: {r["error"]} (node log: {log_dir / (r["tag"] + "_node.log")})')


# ------------------------------------------------------------------ two nodes, one trajectory
def run_two_node(ros: RosClient, log_dir: pathlib.Path, sample_hz: float,
                 steps_s: list[float]) -> dict:
    """One four-joint trajectory, each node its two joints' part with one header.stamp."""
    results: dict[str, Any] = {'part': 'two_node', 'vendor': 'two_node', 'nodes': {},
                               'trajectories': []}
    buses: dict[str, Bus] = {}
    try:
        for key in TWO_NODE:
            buses[key] = bring_up(VENDORS[key], ros, log_dir, f'two_node_{key}', sample_hz, [])
            results['nodes'][key] = {'rate_hz': buses[key].rate_hz,
                                     'transaction_s': buses[key].transaction_s,
                                     'transaction_what': buses[key].transaction_what,
                                     'joints': buses[key].joints}
        # one poll period of each node plus one line transaction (the slower line's: RD4)
        bound = sum(1.0 / b.rate_hz for b in buses.values()) + max(
            b.transaction_s for b in buses.values())
        results['bound_s'] = bound
        for dt in steps_s:
            res: dict[str, Any] = {'dt_s': dt, 'duration_s': TWO_NODE_DURATION_S,
                                   'limit_s': moveit_limit_s(TWO_NODE_DURATION_S)}
            results['trajectories'].append(res)
            try:
                res.update(_two_node_one(buses, ros, dt, sample_hz, bound))
            except Exception as exc:  # noqa: BLE001 - reported in the results, run goes on
                res['error'] = f'{type(exc).__name__}: {exc}'
                results['error'] = f'{dt:g} s: {res["error"]}'
                break
        if 'error' not in results:
            for b in buses.values():
                b.disable(ros)
        results['load'] = os.getloadavg()[0]
        results['cores'] = os.cpu_count()
    finally:
        for b in reversed(list(buses.values())):
            b.close(ros)
    report_two_node(results, log_dir)
    return results


def point_arrivals(buses: dict[str, Bus], axes: list[tuple[str, str]], points: list,
                   start: list[float], steps: dict, start_t: float) -> list[dict]:
    """Arrival at each point: when each axis passes the point's whole-step position, how late
    against the point's time, and the spread over the axes."""
    arrivals = []
    for k in range(1, len(points)):
        due = start_t + points[k][0]
        at, missed, bracket = {}, [], 0.0
        for c, (key, d) in enumerate(axes):
            conv = buses[key].convs[d]
            first, target = round(conv.to_steps(start[c])), round(conv.to_steps(points[k][1][c]))
            if target == first:
                continue                           # still its start step: nothing to pass
            sign = 1.0 if conv.to_steps(points[-1][1][c]) > conv.to_steps(start[c]) else -1.0
            hit = crossing(steps[(key, d)], target, sign)
            if hit is None:
                missed.append(f'{key}/{d}')
            else:
                at[f'{key}/{d}'] = hit[0] - due
                bracket = max(bracket, hit[1])
        spread = max(at.values()) - min(at.values()) if len(at) >= 2 and not missed else None
        arrivals.append({'k': k, 'time_s': points[k][0], 'late_s': at, 'missed': missed,
                         'axes': len(at) + len(missed), 'spread_s': spread,
                         'bracket_s': bracket})
    return arrivals


def _two_node_one(buses: dict[str, Bus], ros: RosClient, dt: float, sample_hz: float,
                  bound: float) -> dict:
    for b in buses.values():
        b.still()
    time.sleep(0.3)
    now = time.monotonic()
    axes = [(key, d) for key in TWO_NODE for d in DRIVES]        # columns of the trajectory
    joints = [buses[key].joints[DRIVES.index(d)] for key, d in axes]
    start = [buses[key].true_rad(d, now) for key, d in axes]
    delta = []
    for n in range(len(TWO_NODE)):
        signs = away(start[2 * n:2 * n + 2])
        delta += [s * x for s, x in zip(signs, LINE_RAD)]
    points = line_points(start, delta, TWO_NODE_DURATION_S, dt)
    marks = {key: buses[key].log_size() for key in TWO_NODE}
    goals: dict[str, ActionGoal] = {}
    try:
        for key in TWO_NODE:               # the servers found before the stamp is taken
            goals[key] = ActionGoal(ros, buses[key].bench.node_name)
        # one stamp, ahead, as MoveIt gives every part of a stamped trajectory
        stamp_ns = ros.node.get_clock().now().nanoseconds + int(TWO_NODE_LEAD_S * 1e9)
        start_t = time.monotonic() + TWO_NODE_LEAD_S
        for n, key in enumerate(TWO_NODE):
            msg = trajectory_msg(joints, points, [2 * n, 2 * n + 1])
            msg.header.stamp = Time(sec=stamp_ns // 1_000_000_000,
                                    nanosec=stamp_ns % 1_000_000_000)
            goals[key].send(FollowJointTrajectory.Goal(trajectory=msg))
        results = {}
        for key in TWO_NODE:
            try:
                results[key] = goals[key].result(
                    start_t - time.monotonic() + moveit_limit_s(TWO_NODE_DURATION_S) + 20.0)
            except RuntimeError:
                raise RuntimeError(f'{key}: no result {time.monotonic() - start_t:.1f} s after '
                                   'the stamp') from None
    finally:
        for g in goals.values():
            g.close()
    time.sleep(0.3)
    t_end = max(g.result_t for g in goals.values())
    samples, steps, dropped = {}, {}, 0
    for key, d in axes:
        kept, left = collect(buses[key].true[d], start_t - TWO_NODE_LEAD_S, t_end,
                             1.0 / sample_hz)
        steps[(key, d)] = kept
        samples[(key, d)] = [(t, buses[key].convs[d].from_steps(x)) for t, x in kept]
        dropped += left
    out: dict[str, Any] = {'points_n': len(points), 'nodes': {}, 'samples_dropped': dropped}
    t_from = min(g.sent_t for g in goals.values())
    for n, key in enumerate(TWO_NODE):
        g, r = goals[key], results[key]
        node_samples = {d: samples[(key, d)] for d in DRIVES}
        fig = polyline_figures(node_samples, DRIVES, [(p[1][2 * n], p[1][2 * n + 1])
                                                      for p in points], t_from, g.result_t)
        fig['timing_max_rad'] = {}
        for i, d in enumerate(DRIVES):
            own = [(p[0], p[1][2 * n + i]) for p in points]
            fig['timing_max_rad'][d] = timing_error(node_samples[d], own, start_t, t_from,
                                                    g.result_t)[0]
        fig.update(merge_line(buses[key].log_since(marks[key])))
        if r.error_code == 0:
            fig['samples_lag_s'] = max(samples_lag(
                node_samples[d], points[-1][1][2 * n + i],
                1.5 / buses[key].convs[d].steps_per_unit, g.result_t)
                for i, d in enumerate(DRIVES))
        fig.update(error_code=r.error_code, error_string=r.error_string,
                   finish_from_stamp_s=g.result_t - start_t, finish_from_sent_s=g.result_t
                   - g.sent_t, sent_before_stamp_s=start_t - g.sent_t)
        out['nodes'][key] = fig
    arrivals = point_arrivals(buses, axes, points, start, steps, start_t)
    spreads = [a['spread_s'] for a in arrivals if a['spread_s'] is not None]
    lates = [x for a in arrivals for x in a['late_s'].values()]
    out.update(arrivals=arrivals, bound_s=bound,
               spread_max_s=max(spreads, default=None),
               spread_median_s=statistics.median(spreads) if spreads else None,
               spread_points=len(spreads), over_bound=sum(s > bound for s in spreads),
               missed_points=sum(bool(a['missed']) for a in arrivals),
               late_min_s=min(lates, default=None), late_max_s=max(lates, default=None),
               bracket_max_s=max((a['bracket_s'] for a in arrivals), default=None),
               samples_lag_s=max(n.get('samples_lag_s', 0.0) for n in out['nodes'].values()),
               samples={f'{key}/{d}': [(round(t - start_t, 4), x) for t, x in samples[(key, d)]]
                        for key, d in axes})
    return out


TWO_NODE_HEADER = ('| points every | result X-PLUS MT; RD4 | finish from the stamp (MoveIt '
                   'limit) | path error max / RMS, X-PLUS MT; RD4 | timing error max, 4 joints '
                   '(mrad) | arrival spread max / median (points) | bound | over the bound | '
                   "arrival vs the point's time |\n|---|---|---|---|---|---|---|---|---|")


def two_node_row(t: dict) -> str:
    if 'nodes' not in t:
        return f'| {t["dt_s"]:g} s | **failed**: {t.get("error", "?")} | | | | | | | |'
    nodes = [t['nodes'][k] for k in TWO_NODE]
    results = '; '.join(code_name(n['error_code']) if n['error_code'] == 0 else
                        f'**{code_name(n["error_code"])}**: {n["error_string"]}' for n in nodes)
    finish = '; '.join(f'{n["finish_from_stamp_s"]:.2f}' for n in nodes)
    over = any(n['finish_from_stamp_s'] > t['limit_s'] for n in nodes)
    path = '; '.join(f'{1000 * n["path_max_rad"]:.1f} / {1000 * n["path_rms_rad"]:.1f} mrad '
                     f'({100 * n["path_max_frac"]:.2f} / {100 * n["path_rms_frac"]:.2f} %)'
                     for n in nodes)
    timing = ' / '.join(f'{1000 * n["timing_max_rad"][d]:.1f}' for n in nodes for d in DRIVES)
    spread = ('-' if t['spread_max_s'] is None else
              f'{1000 * t["spread_max_s"]:.1f} / {1000 * t["spread_median_s"]:.1f} ms '
              f'({t["spread_points"]})')
    late = ('-' if t['late_min_s'] is None else
            f'{1000 * t["late_min_s"]:+.0f}..{1000 * t["late_max_s"]:+.0f} ms')
    if t.get('samples_lag_s', 0) > 0:
        results += f' (samples late by {t["samples_lag_s"]:.2f} s: figures **not valid**)'
    return (f'| {t["dt_s"]:g} s ({t["points_n"] - 1} points) | {results} | {finish} s '
            f'({"**over**" if over else "within"} {t["limit_s"]:.2f}) | {path} | {timing} | '
            f'{spread} | {1000 * t["bound_s"]:.1f} ms | {t["over_bound"]}'
            + (f', {t["missed_points"]} point(s) not reached' if t['missed_points'] else '')
            + f' | {late} |')


def report_two_node(r: dict, log_dir: pathlib.Path) -> None:
    print(f'\n== Two nodes, one trajectory: X-PLUS MT + Lika RD4 [{r.get("cores")} cores, load '
          f'{r.get("load", float("nan")):.2f}]')
    for key, n in r['nodes'].items():
        print(f'   {VENDORS[key].title}: {VENDORS[key].line}; node at {n["rate_hz"]:g} Hz; one '
              f'line transaction {1000 * n["transaction_s"]:.2f} ms')
    if 'bound_s' in r:
        print(f'   header.stamp {TWO_NODE_LEAD_S:g} s ahead, both parts; {TWO_NODE_DURATION_S:g}'
              f' s quintic line, 2.0 / 1.0 rad per node; bound {1000 * r["bound_s"]:.1f} ms')
    print(TWO_NODE_HEADER)
    for t in r['trajectories']:
        print(two_node_row(t))
    for t in r['trajectories']:
        for key, n in t.get('nodes', {}).items():
            extra = [f'sent {n["sent_before_stamp_s"]:.3f} s before the stamp, result '
                     f'{n["finish_from_sent_s"]:.2f} s after sent']
            if n.get('segments') is not None:
                extra.append(f'{n["points"]} points as {n["segments"]} segments (>= '
                             f'{n["min_segment_s"]:.3g} s), plan within {n.get("merge_far")}')
            extra += [f'node: {w[-200:]}' for w in n.get('warnings', [])]
            print(f'   {t["dt_s"]:g} s, {key}: ' + '; '.join(extra))
        if t.get('bracket_max_s') is not None:
            print(f'   {t["dt_s"]:g} s: the two samples around a crossing at most '
                  f'{1000 * t["bracket_max_s"]:.0f} ms apart; {t["samples_dropped"]} samples left '
                  'out (late)' + (f'; NOT VALID: the samples show a joint at its goal '
                                  f'{t["samples_lag_s"]:.2f} s after its result (this process '
                                  'fell behind the samples)' if t['samples_lag_s'] > 0 else ''))
        for a in t.get('arrivals', []):
            if a['missed'] or (a['spread_s'] is not None and a['spread_s'] > t['bound_s']):
                print(f'   {t["dt_s"]:g} s, point {a["k"]} ({a["time_s"]:g} s): '
                      + ', '.join(f'{j} {1000 * x:+.0f} ms' for j, x in a['late_s'].items())
                      + f' (samples {1000 * a["bracket_s"]:.0f} ms apart)'
                      + (f'; never reached: {a["missed"]}' if a['missed'] else ''))
    if 'error' in r:
        print(f'   FAILED: {r["error"]} (node logs: {log_dir}/two_node_*_node.log)')


def summary(runs: list[dict]) -> None:
    """The dense and two-node figures of every bus again, in one table each."""
    dense = [r for r in runs if r.get('part') == 'dense']
    if dense:
        print(f'\n== MoveIt-like dense trajectories, every bus ({DENSE_DURATION_S:g} s, MoveIt '
              f'limit {moveit_limit_s(DENSE_DURATION_S):.1f} s)')
        print(DENSE_HEADER)
        for r in dense:
            spec = VENDORS[r['vendor']]
            title = spec.title + ('' if r.get('sync_period_s') is None
                                  else f', SYNC {r["sync_period_s"]:g} s')
            if not r.get('trajectories'):
                print(f'| {title} | | **failed**: {r.get("error")} | | | | | |')
            for t in r.get('trajectories', []):
                print(dense_row(title, t))
    for r in runs:
        if r.get('part') == 'two_node':
            print('\n== Two nodes (X-PLUS MT + Lika RD4), one trajectory, one stamp '
                  f'{TWO_NODE_LEAD_S:g} s ahead ({TWO_NODE_DURATION_S:g} s, MoveIt limit '
                  f'{moveit_limit_s(TWO_NODE_DURATION_S):.2f} s from the stamp)')
            print(TWO_NODE_HEADER)
            if not r.get('trajectories'):
                print(f'| | **failed**: {r.get("error")} | | | | | | | |')
            for t in r.get('trajectories', []):
                print(two_node_row(t))


def from_json(path: pathlib.Path) -> int:
    """The dense tables of a --json file, the figures its samples give computed again."""
    runs = json.loads(path.read_text())['runs']
    for r in runs:
        for t in r.get('trajectories', []):
            if r.get('part') == 'dense' and 'samples' in t and 'start_rad' in t:
                points = dense_points(t['kind'], t['start_rad'], t['dt_s'])
                t.update(stall_figures(t['samples'], points, t.get('step_rad')))
    summary(runs)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', nargs='+', choices=list(VENDORS), default=list(VENDORS))
    ap.add_argument('--trajectories', type=int, default=3, help='per vendor (default 3)')
    ap.add_argument('--sample-rate', type=float, default=200.0,
                    help="the simulators' true-position rate [Hz] (default 200)")
    ap.add_argument('--band', type=float, default=0.005,
                    help="arrival band, fraction of the axis's segment distance (default 0.005)")
    ap.add_argument('--vector-sync-period', type=float, nargs='*', default=None,
                    help='Vector Step also with can.sync_period_s = each of these [s] '
                         '(interpolated position; default 0.01, with --dense none; none: only '
                         'config/)')
    ap.add_argument('--dense', action='store_true',
                    help='only the MoveIt-like dense trajectories (with --two-node: both)')
    ap.add_argument('--two-node', action='store_true',
                    help='only the two-node trajectory, X-PLUS MT + RD4 (with --dense: both)')
    ap.add_argument('--dt', type=float, nargs='+', default=[0.1, 0.05],
                    help='--dense: a point every S seconds (default 0.1 0.05)')
    ap.add_argument('--kinds', nargs='+', choices=DENSE_KINDS, default=list(DENSE_KINDS),
                    help='--dense: line, arc (default both)')
    ap.add_argument('--two-node-dt', type=float, nargs='+', default=[0.8, 0.1],
                    help='--two-node: a point every S seconds (default 0.8 0.1)')
    ap.add_argument('--node-param', action='append', default=[], metavar='NAME:=VALUE',
                    help='a parameter for the nodes of the dense runs (repeat for more), e.g. '
                    'constraints.xmind_joint1.path_bound:=0.1')
    ap.add_argument('--json', type=pathlib.Path, help='write every figure to this file')
    ap.add_argument('--from-json', type=pathlib.Path,
                    help="no run: the dense tables again from a --json file's samples (stall "
                         'share and timing in %% of travel for a file written before they were)')
    args = ap.parse_args()
    NODE_PARAMS.extend(args.node_param)
    if args.from_json:
        return from_json(args.from_json)
    sparse = not (args.dense or args.two_node)
    syncs = args.vector_sync_period
    if syncs is None:
        syncs = [0.01] if sparse else []
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_traj_'))
    domain_lock = reserve_domain()      # noqa: F841 - held until the end of the run
    print(f'trajectory benchmark: {machine()}; ROS_DOMAIN_ID '
          f'{os.environ.get("ROS_DOMAIN_ID", "0")}; true positions at {args.sample_rate:g} Hz; '
          f'arrival band {100 * args.band:g} % of the segment distance (>= 1 step); logs '
          f'{log_dir}')
    jobs = []
    for part in (['sparse'] if sparse else []) + (['dense'] if args.dense else []):
        for key in args.vendor:
            jobs.append((part, key, None))
            if key == 'vector_step':
                jobs += [(part, key, s) for s in syncs]
    if args.two_node:
        jobs.append(('two_node', None, None))
    results: dict[str, Any] = {'machine': machine(), 'runs': []}
    failed = 0
    ros = RosClient('bench_trajectory')
    try:
        for part, key, sync in jobs:
            try:
                if part == 'sparse':
                    r = run_vendor(VENDORS[key], ros, log_dir, args.trajectories,
                                   args.sample_rate, args.band, sync)
                elif part == 'dense':
                    r = run_dense(VENDORS[key], ros, log_dir, args.sample_rate, args.kinds,
                                  args.dt, sync)
                else:
                    r = run_two_node(ros, log_dir, args.sample_rate, args.two_node_dt)
                results['runs'].append(r)
                failed += 'error' in r
            except Exception as exc:  # noqa: BLE001 - report, go on with the next one
                failed += 1
                what = f'{key or part}{"" if sync is None else f" sync {sync:g}"}'
                print(f'\n== {what} ({part}): FAILED: {exc} (logs in {log_dir})', flush=True)
                results['runs'].append({'part': part, 'vendor': key, 'sync_period_s': sync,
                                        'error': str(exc)})
            sys.stdout.flush()
    finally:
        ros.close()
    summary(results['runs'])
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
