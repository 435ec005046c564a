"""Follower (motion/follow.py) on the X-MIND K simulator with the timing of a 9600 baud line (§3),
through a real BusOwner, no ROS.

Segments (a trajectory no chain can follow: here one faster than the unramped runs): the two
joints of a trajectory on one line start each segment in one instant by one broadcast 99PS where
broadcast_start is true and the line probe found no other drive (capabilities.GroupStarting,
vendors/xmind_k/group.py start_together), else each with its own PS, one transaction apart; a
stop of one joint during the start leaves it unstarted and the run ends aborted with its joints
stopped.

Chains (capabilities.Chaining, motion/chain.py, start_chained): a dense trajectory runs as one
chain of runs per drive in the RAM cells 228-230, without a stop between the runs; by one
broadcast where it may go; a stop ends a chain; a chain with a cell its drive did not confirm is
not started.

The truth is the simulator's: the instants its axes began their runs (`motion_starts`) and the
strings on the wire (its tap).
"""

import time

import pytest
from rigs_motion import quintic_line
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
# j1's first segment needs 3333 Hz: above the fastest chained run (group.CHAIN_MAX_HZ), so the
# trajectory goes as segments
POINTS = [[5000, -2000], [500, 1000]]


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
        # as the node makes them: a move's cost is the drive's estimate until one is measured
        self.follower = Follower({j: Axis(j, n, self.bus_owner, self.drives[n], LIMITS,
                                          move_time_s=self.drives[n].move_time_s())
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
    assert len(rig.starts('a1')) <= 1 and abs(rig.true('a1')) < 5000


# ------------------------------------------------------------------------------------ chains
TRAVEL = [600, 300]                  # steps: j1 up to 375 Hz, j2 188 Hz on the quintic line


def stored_runs(rig, address):
    """The runs written to a drive, in the order written: (cell, code, frequency or delay,
    steps, next cell) from its WN strings (§4.1.6: 21,FFFF,+n,x1,DDD; §4.1.12: 65,ms,DDD)."""
    out = []
    for text in rig.strings('WN'):
        if text[:2] != f'{address:02d}':
            continue
        f = text[4:].split(',')
        if f[2] == '21':
            out.append((int(f[1]), 21, int(f[3]), int(f[4]), int(f[6])))
        else:
            out.append((int(f[1]), int(f[2]), int(f[3]), 0, int(f[-1])))
    return out


def chain_of(rig, address):
    """The drive's last chain, run by run from cell 228: [(steps, frequency_hz)]."""
    cells = {}
    for cell, code, f, steps, nxt in stored_runs(rig, address):
        cells[cell] = (code, f, steps, nxt)
    out, cell = [], 228
    while cell in cells:
        code, f, steps, nxt = cells[cell]
        out.append((steps, f) if code == 21 else (0, f))
        cell = nxt if nxt else None
    return out


def test_a_dense_trajectory_runs_as_one_chain_per_drive_without_a_stop(rig_factory):
    """No broadcast: each drive gets its runs in 230, 229, then 228 (chained by their next
    cell), then its PS; the simulated axis starts each run the instant the one before ends
    (no stop, no string between), and the chain ends at the trajectory's end."""
    rig = rig_factory(False)
    rig.wire.clear()
    run = rig.follower.follow(quintic_line(JOINTS, TRAVEL, 3.0, 0.1))
    assert 'one chain of 3 runs' in run.merge_summary()
    outcome = run.done.result(10.0)
    assert outcome.status == 'succeeded', outcome
    assert sorted(rig.strings('PS')) == ['01PS,228', '02PS,228']
    for name, address, travel in (('a1', 1, TRAVEL[0]), ('a2', 2, TRAVEL[1])):
        assert [(c, n) for c, _, _, _, n in stored_runs(rig, address)] == \
            [(230, 0), (229, 230), (228, 229)]
        chain = chain_of(rig, address)
        assert sum(steps for steps, _ in chain) == travel == rig.true(name)
        starts = rig.starts(name)
        assert len(starts) == 3
        for (steps, f), t0, t1 in zip(chain, starts, starts[1:]):
            # the next run began when this one's steps were done: back to back
            assert t1 - t0 == pytest.approx(abs(steps) / f, abs=0.002)
        # the last run ends at the trajectory's end, within what the Table 4 grid allows its
        # rate (the next frequency up: 1 Hz apart below 300 Hz) and one PS transaction (the
        # first run is timed from an estimate of when the strings still to go end)
        steps, f = chain[-1]
        end = starts[-1] + abs(steps) / f
        assert abs(end - (run.start_t + 3.0)) <= \
            abs(steps) / f - abs(steps) / (f + 1) + PS_TRANSACTION_S


def test_with_broadcast_start_the_chains_start_in_one_instant(rig_factory):
    rig = rig_factory(True)
    assert 'no broadcast' not in rig.probe()
    rig.wire.clear()
    run = rig.follower.follow(quintic_line(JOINTS, TRAVEL, 3.0, 0.05))
    outcome = run.done.result(10.0)
    assert outcome.status == 'succeeded', outcome
    assert rig.strings('PS') == ['99PS,228']
    ps_t = [t for t, text in rig.wire if text == '99PS,228'][0]
    assert all(t < ps_t for t, text in rig.wire if text[2:4] == 'WN')
    assert abs(rig.starts('a2')[0] - rig.starts('a1')[0]) < CHAR_S
    assert rig.true('a1') == TRAVEL[0] and rig.true('a2') == TRAVEL[1]


def test_a_cancel_during_a_chain_stops_the_drives_and_no_later_run_starts(rig_factory):
    rig = rig_factory(False)
    run = rig.follower.follow(quintic_line(JOINTS, TRAVEL, 3.0, 0.1))
    wait_for(lambda: len(rig.starts('a1')) >= 2, 5.0, "a1's second run")
    run.cancel('operator')
    assert run.done.result(5.0).status == 'canceled'
    for name in ('a1', 'a2'):
        wait_for(lambda name=name: not rig.drives[name].in_motion, 3.0, f'{name} stopped')
    ee = [text for text in rig.strings('EE')]
    assert '01EE' in ee
    starts, at = {n: rig.starts(n) for n in ('a1', 'a2')}, {n: rig.true(n) for n in ('a1', 'a2')}
    time.sleep(0.3)
    assert {n: rig.starts(n) for n in ('a1', 'a2')} == starts
    assert {n: rig.true(n) for n in ('a1', 'a2')} == at
    assert at['a1'] < TRAVEL[0]


def test_a_chain_whose_cell_was_not_confirmed_is_not_started(rig_factory):
    """a2's WN 229 and its repeat get no answer: 229 holds what the drive may or may not have
    stored, and PS 228 would run on into it. a2 gets no PS; the run ends aborted naming j2 and
    stops j1, which had started."""
    rig = rig_factory(False)
    rig.wire.clear()

    def lose(text):
        if text.startswith('02WN,229'):
            rig.line.set_link_fault('no_reply', 2)
    rig.on_wire = lose
    run = rig.follower.follow(quintic_line(JOINTS, TRAVEL, 3.0, 0.1))
    outcome = run.done.result(10.0)
    assert outcome.status == 'aborted' and outcome.code == INVALID_GOAL, outcome
    assert 'j2: its chain did not go out' in outcome.text
    assert '02PS,228' not in rig.strings('PS') and rig.starts('a2') == []
    wait_for(lambda: not rig.drives['a1'].in_motion, 3.0, 'a1 stopped')
    assert rig.true('a2') == 0 and rig.true('a1') < TRAVEL[0]
