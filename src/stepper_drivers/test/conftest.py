"""The driver unit tests check every write to a bus owner's slots against its writer rules
(owner/slot.py): a write from the wrong thread fails the test that made it."""

import os

os.environ['STEPPER_DRIVERS_CHECK_WRITERS'] = '1'

from stepper_drivers.owner import slot  # noqa: E402 - after the variable it reads

slot.check_writers()
