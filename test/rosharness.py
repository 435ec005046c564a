"""Test harness: the project's own process and ROS client helpers (see stepper_drivers.tools)."""

from stepper_drivers.tools.client import RosClient  # noqa: F401
from stepper_drivers.tools.processes import (CONFIG, INSTALL, ROOT, Proc, executable,  # noqa: F401
                                             free_port, wait_for)
