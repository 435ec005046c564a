"""Follower (motion/follow.py) on the X-MIND K simulator with the timing of a 9600 baud line (§3),
through a real BusOwner, no ROS: the two joints of a trajectory on one line start each segment in
one instant by one broadcast 99PS where broadcast_start is true and the line probe found no other
drive (capabilities.GroupStarting, vendors/xmind_k/group.py start_together), else each with its own
PS, one transaction apart; a stop of one joint during the start leaves it unstarted and the run
ends aborted with its joints stopped.

The truth is the simulator's: the instants its axes began their runs (`motion_starts`) and the
strings on the wire (its tap).
"""

import time

import pytest
from stepper_drivers.motion.follow import INVALID_GOAL, Axis, Follower
from stepper_drivers.motion.trajectory import JointLimits, build
from stepper_drivers.owner import BusOwner
from stepper_drivers.owner.commands import Command
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.vendors import xmind_k as v
from stepper_sim.harness import wait_for
from stepper_sim.xmind_k.sim import build_line

CHAR_S = xk.char_time_s()          # 1.04 ms a character at 9600 baud (§3)
PS_TRANSACTION_S = 13 * CHAR_S     # one PS and its Y: 9 + 4 characters
BUS = {'baudrate': 9600, 'parity': 'N', 'stopbits': 1, 'timeout_s': 0.03, 'retries': 1,
       'local_echo': False, 'broadcast_probe_wait_ms': xk.RD_DEFAULT_MS}
DRIVE = {'resolution': '', 'current_preset': -1, 'answer_delay_ms': -1, 'equalization': -1,
         'power_cycle_flag': 'F7', 'busy_poll_period_s': 0.05, 'status_poll_period_s': 0.5,
         'steps_per_rev': 2000.0, 'homing.method': 3}
LIMITS = JointLimits(min_steps=-1e6, max_steps=1e6, max_velocity_steps_s=8000.0,
                     max_acceleration_steps_s2=100_000.0, min_velocity_steps_s=1.0)
JOINTS = ['j1', 'j2']
TIMES = [1.5, 3.0]
POINTS = [[3000, -2000], [500, 1000]]


class Rig:
    """Two simulated drives on one line, driven by one owner; j1 -> a1 (01), j2 -> a2 (02)."""

    def __init__(self, tmp_path, broadcast_start):
        self.wire: list[tuple[float, str]] = []
        self.on_wire = None
        self.line = build_line({'port': str(tmp_path / 'tty'), 'line_timing': True},
                               {'a1': {'address': 1}, 'a2': {'address': 2}})
        self.line.tap = self._tap
        self.line.start()
        self.bus = v.make_bus({**BUS, 'broadcast_start': broadcast_start,
                               'port': self.line.link_path})
        self.drives = {n: v.make_drive(self.bus, n, {**BUS, **DRIVE, 'address': a})
                       for n, a in (('a1', 1), ('a2', 2))}
        self.bus_owner = BusOwner(self.bus, self.drives, {
            'publish_rate_hz': 10.0, 'command_timeout_s': 0.5, 'reconnect_period_s': 0.2})
        self.bus_owner.start()
        wait_for(lambda: all(s.connected and s.polls for s in self.bus_owner.slots.values()), 5.0,
                 'both drives connected')
        for n, d in self.drives.items():
            self.bus_owner.submit(n, Command.enable(d.enable)).result(5.0)
        self.follower = Follower({j: Axis(j, n, self.bus_owner, self.drives[n], LIMITS)
                                  for j, n in (('j1', 'a1'), ('j2', 'a2'))})

    def _tap(self, direction, data, t):
        if direction == 'rx':
            text = data.decode('ascii', errors='replace').rstrip('\r')
            self.wire.append((t, text))
            if self.on_wire is not None:
                self.on_wire(text)

    def probe(self):
        """The line probe as the node queues it once a drive connected (node._on_connected)."""
        check = self.bus.group_start_check()
        assert check is not None
        return self.bus_owner.submit('a1', Command.maintenance(check, 'line probe')).result(10.0)

    def strings(self, code):
        return [s for _, s in self.wire if s[2:4] == code]

    def starts(self, name):
        with self.line.lock:
            return [t for t, _ in self.line.by_name[name].motion_starts]

    def true(self, name):
        with self.line.lock:
            return self.line.by_name[name].true_position_steps()

    def close(self):
        self.bus_owner.shutdown(1.0, disable=self.drives)
        self.line.stop()


@pytest.fixture
def rig_factory(tmp_path):
    rigs = []

    def make(broadcast_start):
        rigs.append(Rig(tmp_path, broadcast_start))
        return rigs[-1]
    yield make
    for r in rigs:
        r.close()


def skews(rig):
    """Per segment, a2's start instant minus a1's (s)."""
    return [t2 - t1 for t1, t2 in zip(rig.starts('a1'), rig.starts('a2'))]


def test_with_broadcast_start_both_joints_begin_each_segment_in_one_instant(rig_factory):
    rig = rig_factory(True)
    assert 'no broadcast' not in rig.probe() and rig.bus.line_probe == frozenset()
    rig.wire.clear()
    run = rig.follower.follow(build(JOINTS, TIMES, POINTS, known=JOINTS))
    outcome = run.done.result(10.0)
    assert outcome.status == 'succeeded', outcome
    assert rig.strings('PS') == ['99PS,228', '99PS,228']        # one broadcast per segment
    assert len(rig.starts('a1')) == len(rig.starts('a2')) == 2
    assert all(abs(s) < CHAR_S for s in skews(rig)), skews(rig)
    assert rig.true('a1') == 500 and rig.true('a2') == 1000


def test_without_broadcast_start_each_joint_gets_its_own_ps_a_transaction_apart(rig_factory):
    """Not opted in: no group start at all (each joint its own move job)."""
    rig = rig_factory(False)
    assert rig.bus.group_start_check() is None                 # nothing to probe
    assert rig.bus.group_start(list(rig.drives.values())) is None
    run = rig.follower.follow(build(JOINTS, TIMES, POINTS, known=JOINTS))
    outcome = run.done.result(10.0)
    assert outcome.status == 'succeeded', outcome
    # each segment: one PS per drive, in the owner's order (the drives take turns)
    assert sorted(rig.strings('PS')) == ['01PS,228'] * 2 + ['02PS,228'] * 2
    assert '99PS,228' not in rig.strings('PS') and len(skews(rig)) == 2
    # a whole move transaction at least (status, WN, PS of the second drive; polls between)
    assert all(abs(s) >= PS_TRANSACTION_S for s in skews(rig)), skews(rig)
    assert rig.true('a1') == 500 and rig.true('a2') == 1000


def test_an_unprobed_line_starts_each_joint_with_its_own_ps(rig_factory):
    rig = rig_factory(True)
    run = rig.follower.follow(build(JOINTS, TIMES, POINTS, known=JOINTS))
    assert run.done.result(10.0).status == 'succeeded'
    assert '99PS,228' not in rig.strings('PS') and len(rig.strings('PS')) == 4


def test_a_stop_of_one_joint_during_the_start_leaves_it_unstarted_and_the_run_aborts(
        rig_factory):
    rig = rig_factory(True)
    rig.probe()
    rig.wire.clear()
    stops = []

    stopped_t = []

    def stop_a2(text):                   # a2's run being stored: its stop comes now
        if text.startswith('02WN,228') and not stops:
            stops.append(rig.follower.stop_axis(rig.follower.axes['j2'], 'operator stop'))
            stops[0].add_done_callback(lambda _: stopped_t.append(time.monotonic()))
    rig.on_wire = stop_a2
    run = rig.follower.follow(build(JOINTS, TIMES, POINTS, known=JOINTS))
    outcome = run.done.result(10.0)
    assert outcome.status == 'aborted' and outcome.code == INVALID_GOAL, outcome
    assert 'j2: its move did not go out' in outcome.text
    assert stops and stops[0].result(2.0) is None
    assert '99PS,228' not in rig.strings('PS') and '02PS,228' not in rig.strings('PS')
    # the stop, an urgent job of a2, ran between the steps of the group job queued under a1:
    # before that job's next string (a1's PS)
    ps_t = [t for t, text in rig.wire if text == '01PS,228']
    assert not ps_t or stopped_t[0] < ps_t[0]
    time.sleep(0.3)
    assert rig.starts('a2') == [] and rig.true('a2') == 0
    # j1 went (its own PS, the broadcast cancelled) and the run stopped it
    wait_for(lambda: not rig.drives['a1'].in_motion, 3.0, 'a1 stopped')
    assert len(rig.starts('a1')) <= 1 and abs(rig.true('a1')) < 3000
