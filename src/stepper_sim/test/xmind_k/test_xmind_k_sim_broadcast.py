"""xmind_k_sim: the broadcast stored instruction execution 99PS (§2.2.1, §4.2.5), over its pty
with the timing of a 9600 baud line (§3).

The client is a raw file descriptor (no driver code). What a broadcast does is read on the
simulator's truth: the instants at which the axes began their runs (`motion_starts`).
"""

import time

import pytest
from stepper_drivers.protocol import xmind_k as xk
from stepper_sim.harness import RawLine
from stepper_sim.xmind_k.sim import XmindKDriveSim, XmindKLine

CHAR_S = xk.char_time_s()          # 1.04 ms a character at 9600 baud (§3)
RUN = '31,050,30,+2000,x1,000'     # 2000 steps at 5 kHz, ramp code 30: about 0.41 s


@pytest.fixture
def rig(tmp_path):
    drives = [XmindKDriveSim('d01', 1), XmindKDriveSim('d02', 2), XmindKDriveSim('d03', 3)]
    line = XmindKLine(drives, str(tmp_path / 'tty'), line_timing=True)
    line.start()
    host = RawLine(line.link_path)
    yield line, host, {d.address: d for d in drives}
    host.close()
    line.stop()


def wait_until(cond, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not (value := cond()):
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.005)
    return value


def starts(line, drive):
    with line.lock:
        return list(drive.motion_starts)


def test_99ps_starts_every_free_drive_in_one_instant_and_nobody_answers(rig):
    line, host, d = rig
    for a in (1, 2, 3):
        assert host.ask(f'{a:02d}WN,228,{RUN}') == f'{a:02d}Y'
    assert host.ask('99PS,228', 0.1) is None                  # §4.4.3: no answer
    wait_until(lambda: all(starts(line, d[a]) for a in (1, 2, 3)), 1.0, 'three runs')
    t = [starts(line, d[a])[0][0] for a in (1, 2, 3)]
    # one string heard by all: the same instant (the per-drive PS of a single start lie a whole
    # transaction apart, 9 + 4 characters and more, test below)
    assert max(t) - min(t) < CHAR_S
    for a in (1, 2, 3):
        assert d[a].counters['broadcasts'] == 1 and d[a].counters['answers'] == 1   # WN only
    wait_until(lambda: host.ask('01QA', 0.05) == '01QA,+2000', 2.0, 'drive 01 at rest')
    assert host.ask('02QA') == '02QA,+2000' and host.ask('03QA') == '03QA,+2000'


def test_per_drive_ps_start_a_transaction_apart(rig):
    line, host, d = rig
    for a in (1, 2):
        assert host.ask(f'{a:02d}WN,228,{RUN}') == f'{a:02d}Y'
    assert host.ask('01PS,228') == '01Y'
    assert host.ask('02PS,228') == '02Y'
    wait_until(lambda: starts(line, d[2]), 1.0, 'run of 02')
    gap = starts(line, d[2])[0][0] - starts(line, d[1])[0][0]
    # §3: the second PS leaves after the first's answer: 9 + 4 characters at least
    assert gap >= 13 * CHAR_S


def test_99ps_does_not_reach_a_busy_drive_and_a_drive_in_protection_does_not_move(rig):
    line, host, d = rig
    assert host.ask(f'01WN,228,{RUN}') == '01Y'
    assert host.ask('02WN,228,32,050,30,+,x1,000') == '02Y'      # a free run, busy until ES
    assert host.ask('03WN,228,' + RUN) == '03Y'
    assert host.ask('02PS,228') == '02Y'
    with line.lock:
        d[3].inject_protection()                                 # FA off (§2.2.4)
    host.send('99PS,228')
    wait_until(lambda: starts(line, d[1]), 1.0, 'run of 01')
    with line.lock:
        assert len(d[2].motion_starts) == 1          # its own PS only: busy hears EE/ES (§3)
        assert d[2].counters['ignored_busy'] == 1
        assert d[3].motion_starts == [] and d[3].true_position_steps() == 0
    assert host.ask('99EE', 0.1) is None             # broadcast emergency stop: all stop
    wait_until(lambda: host.ask('02QA', 0.05) is not None, 2.0, 'drive 02 answering')


def test_99ps_instants_differ_by_the_answer_delay(rig):
    """§4.2.2.5 Note: RD delays the execution of every serial command, a broadcast too."""
    line, host, d = rig
    assert host.ask('02WS,RD,40') == '02Y'
    for a in (1, 2):
        assert host.ask(f'{a:02d}WN,228,{RUN}') == f'{a:02d}Y'
    host.send('99PS,228')
    wait_until(lambda: starts(line, d[1]) and starts(line, d[2]), 1.0, 'both runs')
    skew = starts(line, d[2])[0][0] - starts(line, d[1])[0][0]
    assert skew == pytest.approx(0.040 - 0.010, abs=CHAR_S)      # RD 40 ms against 10 ms
