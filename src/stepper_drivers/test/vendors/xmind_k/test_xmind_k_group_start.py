"""X-MIND K group start (vendors/xmind_k.py start_together, probe_line) against xmind_k_sim
over a real pty with the timing of a 9600 baud line (§3), in one process (no ROS).

The simulator's tap records every host string (what went on the wire) and its drives record
the instants their axes began to run (the truth): two axes started by one broadcast 99PS begin
in the same instant; every case the node cannot make safe starts each drive with its own PS, and
no drive that nobody commanded moves.
"""

import time

import pytest
from stepper_drivers.contract.drive import Motion, complete
from stepper_drivers.protocol import xmind_k as xk
from stepper_drivers.vendors import xmind_k as v
from stepper_sim.core.faults import NO_REPLY
from stepper_sim.xmind_k.sim import build_line

CHAR_S = xk.char_time_s()          # 1.04 ms a character at 9600 baud (§3)
# one PS and its Y: 9 + 4 characters; per-drive starts lie at least this far apart
PS_TRANSACTION_S = 13 * CHAR_S
BUS = {'baudrate': 9600, 'parity': 'N', 'stopbits': 1, 'timeout_s': 0.03, 'retries': 1,
       'local_echo': False}
DRIVE = {'resolution': '', 'current_preset': -1, 'answer_delay_ms': -1, 'equalization': -1,
         'power_cycle_flag': 'F7', 'busy_poll_period_s': 0.02, 'status_poll_period_s': 0.2,
         'steps_per_rev': 2000.0, 'homing.method': 3}
FAST = Motion(10000.0, 200000.0, 200000.0)       # 31,100,30: 10 kHz, ramp code 30
RUN = xk.Instruction.make(31, frequency_x100=50, ramp_code=30, steps=700, multiplier='x1')


def wait_until(cond, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not (value := cond()):
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.002)
    return value


class Rig:
    """A line of simulated drives (`sims`: name -> address), the node driving `driven` of
    them; every driven drive connected and enabled."""

    def __init__(self, tmp_path, sims, driven, **bus_params):
        self.wire: list[str] = []
        self.line = build_line({'port': str(tmp_path / 'tty'), 'line_timing': True},
                               {name: {'address': a} for name, a in sims.items()})
        self.line.tap = self._tap
        self.line.start()
        self.bus = v.make_bus({**BUS, **bus_params, 'port': self.line.link_path})
        self.drives = {name: v.make_drive(self.bus, name, {**BUS, **DRIVE,
                                                           'address': sims[name]})
                       for name in driven}
        self.bus.open()
        for d in self.drives.values():
            complete(d.connect())
            complete(d.enable())
        self.wire.clear()

    def _tap(self, direction, data, _t):
        if direction == 'rx':
            self.wire.append(data.decode('ascii', errors='replace').rstrip('\r'))

    def sim(self, name):
        return self.line.by_name[name]

    def starts(self, name):
        with self.line.lock:
            return [t for t, _ in self.sim(name).motion_starts]

    def true(self, name):
        with self.line.lock:
            return self.sim(name).true_position_steps()

    def settle(self, name):
        d = self.drives[name]
        return wait_until(lambda: (s := complete(d.read_state())) and not s.moving and s, 10.0,
                          f'{name} at rest')

    def probe(self):
        """The whole line, waiting for the simulators' RD of 10 ms (the default waits 255)."""
        return complete(v.probe_line(self.bus, rd_ms=xk.RD_DEFAULT_MS, slack_s=0.02))

    def group(self, targets):
        return [v.GroupMove(self.drives[n], t, FAST) for n, t in targets.items()]

    def close(self):
        self.bus.close()
        self.line.stop()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path, {'a1': 1, 'a2': 2}, ['a1', 'a2'], broadcast_start=True)
    yield r
    r.close()


def test_two_axes_start_in_one_instant_by_one_broadcast(rig):
    assert rig.probe() == frozenset() and rig.bus.line_probe == frozenset()
    rig.wire.clear()
    result = complete(v.start_together(rig.group({'a1': 4000, 'a2': -3000})))
    assert result.broadcast and result.why_not == '' and result.started == ('a1', 'a2')
    wait_until(lambda: '99PS,228' in rig.wire, 1.0, 'the broadcast through the line')
    moves = [s for s in rig.wire if s[2:4] in ('WN', 'PS')]
    assert moves == ['01WN,228,31,100,30,+4000,x1,000', '02WN,228,31,100,30,-3000,x1,000',
                     '99PS,228']
    wait_until(lambda: rig.starts('a1') and rig.starts('a2'), 1.0, 'both runs')
    (t1,), (t2,) = rig.starts('a1'), rig.starts('a2')
    assert abs(t1 - t2) < CHAR_S          # one string heard by both: one instant
    assert result.sent_t == pytest.approx(t1 - xk.TURNAROUND_S - 0.010, abs=0.01)
    s = complete(rig.drives['a1'].read_state())
    assert s.moving and s.position_estimated
    assert rig.settle('a1').position_steps == 4000 and rig.true('a1') == 4000
    assert rig.settle('a2').position_steps == -3000 and rig.true('a2') == -3000


def test_without_broadcast_start_each_drive_gets_its_own_ps(tmp_path):
    r = Rig(tmp_path, {'a1': 1, 'a2': 2}, ['a1', 'a2'])
    try:
        r.probe()
        r.wire.clear()
        result = complete(v.start_together(r.group({'a1': 4000, 'a2': -3000})))
        assert not result.broadcast and 'broadcast_start' in result.why_not
        assert result.started == ('a1', 'a2')
        assert [s for s in r.wire if s[2:4] == 'PS'] == ['01PS,228', '02PS,228']
        wait_until(lambda: r.starts('a1') and r.starts('a2'), 1.0, 'both runs')
        assert r.starts('a2')[0] - r.starts('a1')[0] >= PS_TRANSACTION_S
        assert r.settle('a2').position_steps == -3000
    finally:
        r.close()


def test_an_unprobed_line_starts_per_drive(rig):
    result = complete(v.start_together(rig.group({'a1': 500, 'a2': 500})))
    assert not result.broadcast and 'probed' in result.why_not
    assert '99PS,228' not in rig.wire and '01PS,228' in rig.wire and '02PS,228' in rig.wire


def test_an_undriven_drive_on_the_line_is_found_and_never_started(tmp_path):
    """Drive 05 is on the line but not this node's; its cell 228 holds a run (a PLC wrote it):
    a broadcast would start it."""
    r = Rig(tmp_path, {'a1': 1, 'a2': 2, 'other': 5}, ['a1', 'a2'], broadcast_start=True)
    try:
        with r.line.lock:
            r.sim('other').ram[228] = RUN
        assert r.probe() == frozenset({5}) and r.bus.foreign == {5}
        r.wire.clear()
        result = complete(v.start_together(r.group({'a1': 4000, 'a2': 4000})))
        assert not result.broadcast and '05' in result.why_not
        assert [s for s in r.wire if s[2:4] == 'PS'] == ['01PS,228', '02PS,228']
        r.settle('a1')
        r.settle('a2')
        assert r.starts('other') == [] and r.true('other') == 0
    finally:
        r.close()


def test_a_drive_of_the_node_left_out_of_the_start_means_per_drive(tmp_path):
    """a3 is this node's but has no part in the start; its cell 228 holds its last run
    (relative, §5.1): a broadcast would run it again."""
    r = Rig(tmp_path, {'a1': 1, 'a2': 2, 'a3': 3}, ['a1', 'a2', 'a3'], broadcast_start=True)
    try:
        r.probe()
        complete(r.drives['a3'].move_to(600, FAST))
        r.settle('a3')
        r.wire.clear()
        result = complete(v.start_together(r.group({'a1': 4000, 'a2': 4000})))
        assert not result.broadcast and 'a3' in result.why_not
        assert '99PS,228' not in r.wire
        r.settle('a1')
        assert len(r.starts('a3')) == 1 and r.true('a3') == 600
        assert not [s for s in r.wire if s.startswith('03') and s[2:4] in ('WN', 'PS')]
    finally:
        r.close()


def test_a_member_that_stays_gets_the_null_instruction_and_does_not_move(tmp_path):
    r = Rig(tmp_path, {'a1': 1, 'a2': 2, 'a3': 3}, ['a1', 'a2', 'a3'], broadcast_start=True)
    try:
        r.probe()
        complete(r.drives['a3'].move_to(600, FAST))          # its cell 228 holds +600
        r.settle('a3')
        r.wire.clear()
        result = complete(v.start_together(r.group({'a1': 4000, 'a2': 4000, 'a3': 600})))
        assert result.broadcast and result.started == ('a1', 'a2')
        wait_until(lambda: '99PS,228' in r.wire, 1.0, 'the broadcast through the line')
        assert '03WN,228,00,000' in r.wire and r.wire[-1] == '99PS,228'
        r.settle('a1')
        r.settle('a3')
        assert len(r.starts('a3')) == 1 and r.true('a3') == 600
    finally:
        r.close()


def test_one_drive_moving_needs_no_broadcast(rig):
    rig.probe()
    rig.wire.clear()
    result = complete(v.start_together(rig.group({'a1': 4000, 'a2': 0})))
    assert not result.broadcast and result.started == ('a1',)
    assert [s for s in rig.wire if s[2:4] in ('WN', 'PS')] == [
        '01WN,228,31,100,30,+4000,x1,000', '01PS,228']


def steps_until(gen, cond):
    """Run the step-wise `gen` (sleeping its delays) until cond() holds between two steps."""
    while not cond():
        delay = next(gen)
        if delay:
            time.sleep(delay)


def test_a_lost_wn_reply_leaves_that_drive_unstarted_and_no_broadcast(rig):
    """Both tries of 02's WN are answered, but the answers are lost: the run may be stored
    (a lost reply is taken as having reached the drive), its cell is unknown to the node."""
    rig.probe()
    rig.wire.clear()
    gen = v.start_together(rig.group({'a1': 4000, 'a2': 4000}))
    steps_until(gen, lambda: '02QO,F7' in rig.wire)
    rig.line.set_link_fault(NO_REPLY, count=2)
    result = complete(gen)
    assert rig.wire.count('02WN,228,31,100,30,+4000,x1,000') == 2
    assert not result.broadcast and 'a2' in result.why_not and 'a2' in result.skipped
    assert result.started == ('a1',)
    assert '99PS,228' not in rig.wire and '02PS,228' not in rig.wire
    rig.settle('a1')
    assert rig.starts('a2') == [] and rig.true('a2') == 0


def test_a_stop_between_the_steps_cancels_the_broadcast_and_that_drive(rig):
    rig.probe()
    rig.wire.clear()
    gen = v.start_together(rig.group({'a1': 4000, 'a2': 4000}))
    steps_until(gen, lambda: '02WN,228,31,100,30,+4000,x1,000' in rig.wire)
    rig.drives['a2'].stop()           # an urgent job of the bus owner runs between the steps
    result = complete(gen)
    assert not result.broadcast and result.started == ('a1',) and 'a2' in result.skipped
    assert '99PS,228' not in rig.wire and '02PS,228' not in rig.wire
    rig.settle('a1')
    assert rig.starts('a2') == []


def test_a_drive_in_protection_is_not_started(rig):
    rig.probe()
    with rig.line.lock:
        rig.sim('a2').inject_protection()                  # FA off (§2.2.4)
    rig.wire.clear()
    result = complete(v.start_together(rig.group({'a1': 4000, 'a2': 4000})))
    assert not result.broadcast and 'a2' in result.skipped
    assert 'protection' in result.skipped['a2']
    assert '99PS,228' not in rig.wire and '02PS,228' not in rig.wire
    assert rig.settle('a1').position_steps == 4000


def test_a_cell_written_behind_the_start_cancels_the_broadcast_and_that_drive(rig):
    """A raw WN (write_register, a maintenance job between the steps) leaves 02's cell 228
    as the node does not know it: neither the broadcast nor its PS may run it."""
    rig.probe()
    rig.wire.clear()
    gen = v.start_together(rig.group({'a1': 4000, 'a2': 4000}))
    steps_until(gen, lambda: '02WN,228,31,100,30,+4000,x1,000' in rig.wire)
    rig.drives['a2'].write_register('WN', 'string', '228,31,100,30,+9000,x1,000')
    result = complete(gen)
    assert not result.broadcast and 'cell 228' in result.why_not
    assert result.started == ('a1',) and 'a2' in result.skipped
    assert '99PS,228' not in rig.wire and '02PS,228' not in rig.wire
    rig.settle('a1')
    assert rig.starts('a2') == []


def test_a_drive_stopped_while_the_start_waited_in_the_queue_is_left_out(rig):
    """The job is queued under a1's name; a2's stop, which comes while it waits, does not drop
    it as it drops a2's own jobs: GroupMove.stops leaves a2 out."""
    rig.probe()
    moves = [v.GroupMove(rig.drives[n], 4000, FAST, stops=rig.drives[n].stops)
             for n in ('a1', 'a2')]
    rig.drives['a2'].stop()
    rig.wire.clear()
    result = complete(v.start_together(moves))
    assert not result.broadcast and result.started == ('a1',) and 'a2' in result.skipped
    assert not [s for s in rig.wire if s.startswith('02') and s[2:4] in ('WN', 'PS')]
    assert '99PS,228' not in rig.wire
    rig.settle('a1')
    assert rig.starts('a2') == []
