"""motion/moves.py's continuous move job, on its own (no bus, no thread): the speed it sends
from where the plan and the last snapshot put the drive."""

import dataclasses
import time
import types

import pytest
from stepper_drivers.contract.drive import Motion
from stepper_drivers.motion.axis import Axis
from stepper_drivers.motion.moves import MoveJobs
from stepper_drivers.motion.trajectory import AxisMove, JointLimits

# An RD4 joint (T48): 1 Hz the least speed it runs at (§6.4 Min. speed), 1066 Hz the most.
LIMITS = JointLimits(min_steps=-1e6, max_steps=1e6, max_velocity_steps_s=1066.0,
                     max_acceleration_steps_s2=4000.0, min_velocity_steps_s=1.0)
LEFT_S = 0.3                  # from the move to the segment's end
SEEN_AGE_S = 0.1              # how old the last snapshot is


class Recorder:
    """A drive that records the motion of each move_to."""

    motion_sent_t = None

    def __init__(self):
        self.moves: list[tuple[int, Motion]] = []

    def move_to(self, target_steps, motion):
        self.moves.append((target_steps, motion))


class SeenAt(Axis):
    """An axis whose last snapshot saw the drive standing at `seen_steps`, `seen_age_s` ago."""

    seen_steps = 0.0
    seen_age_s = 0.0

    def sample_motion(self):
        return self.seen_steps, 0.0, time.monotonic() - self.seen_age_s


def last_move_speed(entry_steps, seen_steps):
    """The speed the job sends for a joint's last move to 163 steps (where it stops), planned
    from entry_steps at 30 Hz, its snapshot at seen_steps SEEN_AGE_S ago."""
    drive = Recorder()
    axis = SeenAt('j', 'axis2', bus_owner=None, drive=drive, limits=LIMITS)
    axis.seen_steps, axis.seen_age_s = seen_steps, SEEN_AGE_S
    jobs = MoveJobs(types.SimpleNamespace(axes={'j': axis}, clock=time.monotonic, current=None))
    move = AxisMove('j', target_steps=163.0, velocity_steps_s=4.7, acceleration_steps_s2=4000.0,
                    via_steps=163.0, entry_steps=entry_steps, entry_velocity_steps_s=30.0)
    now = time.monotonic()
    job = jobs._continuous_job(axis, move, seg_t=now, end_t=now + LEFT_S)()
    for _ in job:                      # (no wait: its instant has come)
        pass
    (target, motion), = drive.moves
    assert target == 163
    return motion.velocity_steps_s


def test_a_last_move_from_a_stale_estimate_does_not_creep():
    """The plan puts the drive half a step short of its end (162.5) while its last snapshot saw
    it 8 steps short 0.1 s ago: the job sends at least the average speed that covers those 8
    steps from the snapshot to the segment's end (0.4 s), not the least speed from the plan's
    estimate (the 1 Hz minimum, 8 steps in 8 s)."""
    v = last_move_speed(entry_steps=162.5, seen_steps=155.0)
    assert v >= (163.0 - 155.0) / (LEFT_S + SEEN_AGE_S) - 0.01, v


def test_a_last_move_whose_snapshot_is_no_farther_back_keeps_its_cruise_speed():
    """Where the snapshot agrees with the estimate (the drive there or beyond), the least
    cruise speed stands."""
    ahead = last_move_speed(entry_steps=150.0, seen_steps=163.0)
    agreeing = last_move_speed(entry_steps=150.0, seen_steps=150.0)
    assert ahead == pytest.approx(agreeing, rel=1e-3)        # (the clock moved in between)


def test_the_catch_up_speed_is_bounded_by_the_joints_max_velocity():
    limits = dataclasses.replace(LIMITS, max_velocity_steps_s=20.0)
    drive = Recorder()
    axis = SeenAt('j', 'axis2', bus_owner=None, drive=drive, limits=limits)
    axis.seen_steps = -1000.0
    jobs = MoveJobs(types.SimpleNamespace(axes={'j': axis}, clock=time.monotonic, current=None))
    move = AxisMove('j', 163.0, 4.7, 4000.0, via_steps=163.0, entry_steps=162.5,
                    entry_velocity_steps_s=0.0)
    now = time.monotonic()
    for _ in jobs._continuous_job(axis, move, now, now + LEFT_S)():
        pass
    assert drive.moves[0][1].velocity_steps_s <= 20.0
