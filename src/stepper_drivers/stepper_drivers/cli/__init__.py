"""stepperctl: the operator's command line for stepper_drivers nodes and buses.

Two halves that share nothing but the exit codes:
- `ros_commands` works through the ROS interface of running driver nodes (list, status, enable,
  move, jog, ...); the drives are found on the ROS graph by their DriveStatus topics.
- `scan` talks to a bus directly (no node running) to find which drives answer at which address,
  and can write a params file for them.
"""

# the exit codes, re-exported (hence F401): the commands' callers import them from the package
from .errors import (  # noqa: F401
                     EXIT_FAILED,
                     EXIT_FAULT,
                     EXIT_NOT_FOUND,
                     EXIT_OK,
                     EXIT_TIMEOUT,
                     EXIT_USAGE,
                     CliError,
)
