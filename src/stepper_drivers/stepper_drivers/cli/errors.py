"""Exit codes of stepperctl and the one exception that carries one (no rclpy here)."""

from __future__ import annotations

EXIT_OK = 0            # done
EXIT_FAILED = 1        # the drive (or the node) refused or failed; the message says why
EXIT_USAGE = 2         # bad arguments (argparse uses 2 too)
EXIT_NOT_FOUND = 3     # no such drive on the ROS graph / nothing answered on the bus
EXIT_TIMEOUT = 4       # no answer, or the target not reached, within the time allowed
EXIT_FAULT = 5         # the drive is in FAULT
EXIT_INTERRUPTED = 130  # Ctrl-C during a motion (the drive was told to stop)

EXIT_NAMES = {EXIT_OK: 'ok', EXIT_FAILED: 'failed', EXIT_USAGE: 'usage',
              EXIT_NOT_FOUND: 'not found', EXIT_TIMEOUT: 'timeout', EXIT_FAULT: 'fault',
              EXIT_INTERRUPTED: 'interrupted'}


class CliError(Exception):
    """Ends the command: `message` is printed as one line on stderr, `code` is the exit code."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code
        self.message = message
