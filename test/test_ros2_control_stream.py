"""ros2_control's topic hardware interface drives every vendor's node (docs/ros2_control.md).

`PluginStream` (rigs_ros2_control.py) publishes exactly what
`joint_state_topic_hardware_interface/JointStateTopicSystem`
(ros-controls/topic_based_hardware_interfaces 1.1.0) sends on its `joint_commands_topic`: on every
controller_manager update (100 Hz here) one sensor_msgs/JointState stamped now, `name` = every
joint of its `<ros2_control>` block in URDF order (here the node's joints and one of another
node: a block that spans two nodes), `position[]` for the joints with a position command
interface (or `velocity[]` for velocity ones), NaN before a controller writes; QoS depth 1,
reliable. Against each vendor's simulator and node, judged by the simulators' true positions and
the node's counters:
- the NaN phase moves nothing and refuses nothing;
- a hold phase (the same targets 100 times a second) costs no transaction beyond the polls;
- a quintic ramp is followed: on the fast links (X-PLUS MT, Vector Step) no farther behind than
  one poll period plus the command's and the measurement's own delays; on the serial lines to
  its end (scripts/bench_ros2_control.py measures the lag against the goal);
- a first 0.0 far from the joints (the older plugin's first command) is refused by the start
  guard, naming the joint, the position, the actual one and the parameter;
- a velocity-only stream that falls silent stops within command_timeout_s;
- the other node's joint is told once in the log (joint_command_shared), not every 5 s;
- /joint_states and the statuses reach a best-effort subscriber (the plugin reads with the
  sensor-data QoS).
"""

from __future__ import annotations

import math
import re
import threading
import time

import pytest
from rigs_ros2_control import RAMP_RAD, RAMP_S, PluginStream, quintic
from rigs_vendors import (
    DECEL_RAD_S2,
    RATE_HZ,
    SIM_TICK_S,
    STEPS_PER_RAD,
    TRANSACTION_S,
    Rd4LineTimingBench,
    make_bench,
)
from rosharness import MIDDLEWARE_S, Track, watchdog_bound_s

TIMEOUT_S = 0.5               # command_timeout_s of every config/<vendor>.yaml
OTHER_JOINT = 'other_node_joint'
FAST = ('xplus_mt', 'vector_step')
VENDORS = ('xplus_mt', 'vector_step', 'rd4', 'xmind_k')


class BusUse:
    """What the bus carried per second over a window: the node's transactions
    (status.link_transactions, between the stamps of two statuses published after the window's
    ends: a cached one may be a status period old); on the CAN bus every frame the broker
    relayed, since a Vector Step set point goes out as RxPDO frames, which are no transactions."""

    def __init__(self, bench, drive):
        self.bench, self.drive = bench, drive

    def sample(self) -> tuple[int, float]:
        broker = getattr(self.bench, 'broker', None)
        if broker is not None:
            return broker.frames_in, time.monotonic()
        st = self.bench.fresh_status(self.drive, what='a status')
        return st.link_transactions, st.header.stamp.sec + st.header.stamp.nanosec * 1e-9

    def rate(self, window_s: float, during=None) -> float:
        first, t_first = self.sample()
        t0 = time.monotonic()
        if during is not None:
            during()
        time.sleep(max(0.0, t0 + window_s - time.monotonic()))
        last, t_last = self.sample()
        assert t_last > t_first, (t_first, t_last)
        return ((last - first) & 0xFFFFFFFF) / (t_last - t_first)


def _when(start: float, x: float, t_ramp: float) -> float:
    """When the ramp from `start` (begun at t_ramp) set the point x."""
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if start + RAMP_RAD * quintic(mid) < x else (lo, mid)
    return t_ramp + lo * RAMP_S


def _true_rad(bench, drive):
    return bench.fresh_true_steps(drive) / STEPS_PER_RAD[bench.vendor]


@pytest.mark.parametrize('vendor', VENDORS)
def test_the_topic_plugins_stream_drives_the_node(vendor, procs, ros, tmp_path):
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from stepper_drivers_msgs.msg import DriveStatus
    args = ('-p', 'joint_command_shared:=true')
    if vendor == 'rd4':      # the real line's timing: a move outlasts the stream's 10 ms
        bench = Rd4LineTimingBench(procs, ros, tmp_path, node_args=args)
    else:
        bench = make_bench(vendor, procs, ros, tmp_path, node_args=args)
    drives = ['axis1', 'axis2']
    if vendor == 'vector_step':
        bench.inject('axis2', 'power_stage_ok')        # the rig starts it blocked
    joints = [bench.status(d).joint_name for d in drives]
    for d in drives:
        bench.enable(d)
    # the plugin reads joint states with the sensor-data QoS (best effort)
    got = {'js': threading.Event(), 'status': threading.Event()}
    subs = [ros.node.create_subscription(JointState, '/joint_states',
                                         lambda m: got['js'].set(), qos_profile_sensor_data),
            ros.node.create_subscription(DriveStatus, f'{bench.node_ns}/axis1/status',
                                         lambda m: got['status'].set(), qos_profile_sensor_data)]
    assert got['js'].wait(5.0) and got['status'].wait(5.0), 'nothing on a best-effort reader'
    for s in subs:
        ros.node.destroy_subscription(s)
    stream = PluginStream(ros, [*joints, OTHER_JOINT])
    start = [_true_rad(bench, d) for d in drives]
    refused = [bench.status(d).commands_refused for d in drives]

    # NaN: no controller has written yet
    stream.run('position', lambda t: [math.nan] * 3, 0.5)
    for i, d in enumerate(drives):
        st = bench.status(d)
        assert st.commands_refused == refused[i], st.last_refusal
        assert not st.moving
        assert _true_rad(bench, d) == pytest.approx(start[i], abs=1.0 / STEPS_PER_RAD[vendor])

    # hold: the positions where the joints stand, 100 times a second. The first message sends
    # each target once; after that the hold costs no transaction beyond the polls.
    hold = [*start, 0.0]
    stream.run('position', lambda t: hold, 0.3)
    use = BusUse(bench, 'axis1')
    idle = use.rate(1.0)
    held = use.rate(1.0, during=lambda: stream.start('position', lambda t: hold))
    stream.stop()
    # the polls' own jitter aside (a fifth): 100 messages a second sent would be 100
    # transactions a second more
    assert held <= idle * 1.2 + 10, (held, idle)
    for i, d in enumerate(drives):
        assert bench.status(d).commands_refused == refused[i]

    # the ramp, both joints
    track = [Track(ros, bench.true_topic(d)) for d in drives]
    t_ramp = time.monotonic()
    stream.run('position', lambda t: [start[0] + RAMP_RAD * quintic(t / RAMP_S),
                                      start[1] + RAMP_RAD * quintic(t / RAMP_S), 0.0],
               RAMP_S + 0.3)
    end = [s + RAMP_RAD for s in start]
    for i, d in enumerate(drives):
        bench.status(d, lambda m, i=i: not m.moving and abs(m.position - end[i]) < 2e-3,
                     timeout_s=15.0, what=f'{d} at the end of the ramp')
        assert bench.status(d).commands_refused == refused[i]
    if vendor in FAST:
        # each true position lies between now's set point and the one of a lag ago: one poll
        # period, the command's way (a middleware hop; the set point and its CiA 402 handshake,
        # two transactions), and the measurement's (the simulator's tick, a middleware hop)
        lag_s = (1.0 / RATE_HZ[vendor] + MIDDLEWARE_S + 2 * TRANSACTION_S[vendor]
                 + SIM_TICK_S[vendor] + MIDDLEWARE_S)
        step = 1.0 / STEPS_PER_RAD[vendor]
        for i, d in enumerate(drives):
            def planned(t, i=i):
                return start[i] + RAMP_RAD * quintic((t - t_ramp) / RAMP_S)
            with track[i].lock:
                samples = [(t, x / STEPS_PER_RAD[vendor]) for t, x in track[i].samples
                           if t_ramp + lag_s <= t <= t_ramp + RAMP_S]
            assert len(samples) > 20
            worst = max(max(planned(t - lag_s) - x, x - planned(t)) for t, x in samples)
            top = 1.875 * RAMP_RAD / RAMP_S
            behind = max(t - _when(start[i], x, t_ramp) for t, x in samples)
            assert worst <= 2 * step, (f'{d}: {worst:.4f} rad behind the lag of {lag_s:.3f} s '
                                       f'(one poll period at {top:.3f} rad/s is '
                                       f'{top / RATE_HZ[vendor]:.4f} rad); the true position '
                                       f'was up to {behind:.3f} s behind the set points')

    # the older plugin's first command: 0.0 for every joint, 1 rad from where they stand
    # command_timeout_s (0.5 s in every config/<vendor>.yaml) without a position: a new stream
    time.sleep(max(0.0, stream.sent[-1][0] + TIMEOUT_S + 0.05 - time.monotonic()))
    before = [bench.status(d).commands_refused for d in drives]
    stream.run('position', lambda t: [0.0, 0.0, 0.0], 0.1)
    for i, d in enumerate(drives):
        st = bench.status(d, lambda m, i=i: m.commands_refused > before[i],
                          what=f'{d}: the 0.0 refused')
        why = st.last_refusal
        assert (f'joint {joints[i]!r}' in why and 'joint_command position 0' in why
                and f'drives.{d}.joint_command_max_start_offset' in why), why
        actual = re.search(r'where the joint stands \(([^)]+)\)', why)
        assert actual and float(actual[1]) == pytest.approx(end[i], abs=2e-3), why
        assert _true_rad(bench, d) == pytest.approx(end[i], abs=2e-3)

    # velocity-only (a velocity command interface), then silence: the watchdog stops it
    vtrack = Track(ros, bench.true_topic('axis1'))
    stream.start('velocity', lambda t: [1.0, math.nan, math.nan])
    bench.status('axis1', lambda m: m.moving and m.watchdog_armed, what='axis1 running')
    t_last = stream.stop()
    bound_s = watchdog_bound_s(TIMEOUT_S, RATE_HZ[vendor], 1.0, DECEL_RAD_S2[vendor],
                               TRANSACTION_S[vendor]) + SIM_TICK_S[vendor]
    still_at = vtrack.wait_still(0.3, bound_s + 3.0, 'axis1 stopped by the watchdog')
    assert still_at - t_last <= bound_s, (still_at - t_last, bound_s)
    assert not bench.status('axis2').moving

    # the other node's joint: told once, and not warned about; the guard's refusals of the
    # 0.0 stream logged once for each joint (one run of like refusals)
    out = bench.node.output()
    assert out.count('starts a stream') == len(drives), out[-3000:]
    assert out.count(f"joint {OTHER_JOINT!r} is not one of this node's") == 1, out[-3000:]
    assert 'unknown joint' not in out, out[-3000:]
