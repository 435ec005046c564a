"""Link noise is not identity: a BusOwner (no ROS) over the scripted drives of
rigs_owner.py and over each vendor's real driver and simulator (rigs_owner_vendors.py).

- An answer that breaks its protocol's format is a LinkError: the drive is DISCONNECTED and
  reconnected on the normal back-off for as long as the noise lasts, never "not driven".
- Only a well-formed answer naming another device (IdentityError) makes a drive not driven;
  the status says when it is checked again, it is checked again on the slow back-off
  (IDENTITY_RECHECK_S doubling up to IDENTITY_RECHECK_MAX_S, shortened here), for as long as
  the node runs, and `recheck()` (fault_reset) checks at once. A drive not driven is never
  commanded.
"""

import re
import time

import pytest
from rigs_owner import SETTINGS, Line, ScriptDrive, counted
from rigs_owner_vendors import Rd4, VectorStep, XmindK, XplusMt
from stepper_drivers import owner
from stepper_drivers.contract.drive import DriveError, IdentityError, LinkError, State
from stepper_drivers.owner import COMMAND, BusOwner, NotConnected
from stepper_drivers.owner.commands import Command
from stepper_sim.harness import wait_for

AT = r'checked again at \d\d:\d\d:\d\d, in {:g} s; fault_reset checks at once'


@pytest.fixture
def fast_recheck(monkeypatch):
    monkeypatch.setattr(owner.slot, 'IDENTITY_RECHECK_S', 0.2)
    monkeypatch.setattr(owner.slot, 'IDENTITY_RECHECK_MAX_S', 0.5)


def scripted(error=None, **settings):
    line = Line()
    drive = ScriptDrive(line, 'axis1')
    if error is not None:
        drive.fail_always['connect'] = error
    events = []
    bus_owner = BusOwner(line, {'axis1': drive}, {**SETTINGS, **settings},
                        on_event=lambda *e: events.append(e))
    calls = counted(drive)
    bus_owner.start()
    return bus_owner, drive, bus_owner.slots['axis1'], calls, events


# ----------------------------------------------------------------------- the bus owner
def test_an_identity_error_is_not_driven_and_checked_again_for_ever(fast_recheck):
    bus_owner, drive, slot, calls, events = scripted(
        IdentityError('1018:02 reads 0x1234: not an X'))
    try:
        wait_for(lambda: slot.not_driven, 2.0, 'not driven')
        assert re.search(r'^1018:02 reads 0x1234: not an X \(' + AT.format(0.2) + r'\)$',
                         slot.not_driven), slot.not_driven
        assert not slot.connected and slot.state.state == State.DISCONNECTED
        # never commanded meanwhile
        with pytest.raises(NotConnected):
            bus_owner.submit('axis1', Command(COMMAND, lambda: drive.move_to(5, None),
                                        'move')).result(1.0)
        wait_for(lambda: len(calls) >= 5, 5.0, 'five identity checks')
        gaps = [b - a for a, b in zip(calls, calls[1:])]
        assert gaps[0] == pytest.approx(0.2, abs=0.15), gaps
        assert gaps[1] == pytest.approx(0.4, abs=0.15), gaps
        assert all(g == pytest.approx(0.5, abs=0.15) for g in gaps[2:4]), gaps   # the cap
        assert re.search(AT.format(0.5), slot.not_driven), slot.not_driven
        assert not bus_owner.bus.calls('axis1', 'move_to')
        drive.fail_always.clear()                            # the right device again
        wait_for(lambda: slot.connected and slot.polls, 2.0, 'driven again')
        assert slot.not_driven == '' and slot.last_error == ''
        assert any('the identity matches again: driven' in e[2] for e in events), events
    finally:
        bus_owner.shutdown(0.5)


def test_noise_is_retried_on_the_reconnect_back_off_and_never_makes_a_drive_not_driven():
    bus_owner, drive, slot, calls, _ = scripted(
        LinkError("'03QS,RS' was answered b'03?S,RS,D2\\r'"), reconnect_period_s=0.02)
    try:
        wait_for(lambda: len(calls) >= 8, 5.0, 'eight connect attempts')   # and more to come
        assert slot.not_driven == '' and not slot.connected
        assert "b'03?S,RS,D2\\r'" in slot.last_error
        assert max(b - a for a, b in zip(calls, calls[1:])) < 0.3       # 8 x 0.02 s at most
        drive.fail_always.clear()
        wait_for(lambda: slot.connected, 1.0, 'connected')
    finally:
        bus_owner.shutdown(0.5)


def test_recheck_connects_at_once_and_says_what_it_found(monkeypatch):
    monkeypatch.setattr(owner.slot, 'IDENTITY_RECHECK_S', 60.0)
    bus_owner, drive, slot, calls, _ = scripted(IdentityError('HW Version reads RD5'))
    try:
        wait_for(lambda: slot.not_driven, 2.0, 'not driven')
        assert re.search(AT.format(60), slot.not_driven)
        with pytest.raises(IdentityError, match='RD5'):
            bus_owner.recheck('axis1').result(2.0)             # checked now, not in a minute
        assert len(calls) == 2 and re.search(AT.format(120), slot.not_driven)
        drive.fail_always['connect'] = LinkError('no answer')   # the device is gone meanwhile
        with pytest.raises(LinkError):
            bus_owner.recheck('axis1').result(2.0)
        assert slot.not_driven == ''                     # nothing is known: DISCONNECTED
        drive.fail_always.clear()
        wait_for(lambda: slot.connected, 2.0, 'connected')
        assert bus_owner.recheck('axis1').result(1.0) == {'serial_number': '7'}
    finally:
        bus_owner.shutdown(0.5)
    with pytest.raises(owner.Cancelled):
        bus_owner.recheck('axis1').result(1.0)                  # after shutdown: at once


def test_a_drive_refused_for_good_stays_refused(fast_recheck):
    """One device configured twice (the node's refuse_drive) is a configuration error: it is
    not connected again, however long the node runs; recheck says so."""
    bus_owner, drive, slot, calls, _ = scripted()
    try:
        wait_for(lambda: slot.connected, 2.0, 'connected')
        bus_owner.refuse_drive('axis1', 'axis1 and axis2 answer with one identity')
        wait_for(lambda: not slot.connected, 2.0, 'dropped')
        n = len(calls)
        time.sleep(0.8)                                   # beyond IDENTITY_RECHECK_MAX_S
        assert len(calls) == n and 'one identity' in slot.not_driven
        with pytest.raises(DriveError, match='not driven: axis1 and axis2'):
            bus_owner.recheck('axis1').result(1.0)
    finally:
        bus_owner.shutdown(0.5)


# ------------------------------------------------ the four vendors (rigs_owner_vendors.py)
VENDORS = {'xmind_k': XmindK, 'rd4': Rd4, 'xplus_mt': XplusMt, 'vector_step': VectorStep}
NOISE_S = 3.0


@pytest.mark.parametrize('vendor', VENDORS)
def test_garbled_identity_answers_for_seconds_then_clean_the_drive_comes_back(tmp_path,
                                                                              vendor):
    rig = VENDORS[vendor](tmp_path)
    slot = rig.supervise()
    try:
        wait_for(lambda: slot.connected and slot.polls, 10.0, 'connected')
        rig.garble()
        wait_for(lambda: not slot.connected, 10.0, 'the link lost to the noise')
        n, end = len(rig.calls), time.monotonic() + NOISE_S
        while time.monotonic() < end:
            assert not slot.connected and slot.not_driven == '', slot.not_driven
            time.sleep(0.01)
        assert len(rig.calls) >= n + 3, 'reconnected on the back-off meanwhile'
        assert re.search(rig.noise, slot.last_error), slot.last_error
        rig.clean()
        wait_for(lambda: slot.connected and slot.polls, 10.0, 'connected again, no restart')
        assert slot.not_driven == ''
    finally:
        rig.close()


@pytest.mark.parametrize('vendor', VENDORS)
def test_a_wrong_identity_is_not_driven_until_the_device_is_right(tmp_path, vendor,
                                                                   fast_recheck):
    rig = VENDORS[vendor](tmp_path, wrong=True)
    slot = rig.supervise()
    try:
        wait_for(lambda: slot.not_driven, 10.0, 'not driven')
        assert re.search(rig.wrong, slot.not_driven) and re.search(AT.format(0.2),
                                                                   slot.not_driven)
        wait_for(lambda: len(rig.calls) >= 3, 10.0, 'checked again, twice')
        assert not slot.connected and slot.not_driven
        with pytest.raises(NotConnected):
            rig.bus_owner.submit(rig.name, Command(COMMAND, rig.drive.enable,
                                                   'enable')).result(2.0)
        rig.make_right()
        wait_for(lambda: slot.connected and slot.polls, 10.0, 'driven again, no restart')
        assert slot.not_driven == ''
        assert not slot.state.enabled            # connecting never enables
    finally:
        rig.close()
