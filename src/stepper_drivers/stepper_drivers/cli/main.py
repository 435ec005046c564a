"""stepperctl: command line entry point (argument parsing, exit codes, one-line errors)."""

from __future__ import annotations

import argparse
import logging
import sys

from .errors import EXIT_INTERRUPTED, EXIT_NAMES, EXIT_USAGE, CliError

logger = logging.getLogger(__name__)

PROG = 'stepperctl'
EPILOG = """exit codes: 0 ok, 1 the drive refused or failed, 2 usage, 3 drive not found / nothing
answered, 4 timeout, 5 drive in fault, 130 interrupted (the drive was told to stop).
Drives are named node/drive (xplus_mt_node/axis1), by drive name alone (axis1) or by joint name
when that names one drive. The ROS commands see the nodes of ROS_DOMAIN_ID within
ROS_AUTOMATIC_DISCOVERY_RANGE, as any ROS tool."""


class Parser(argparse.ArgumentParser):
    """argparse with a one-line usage error (the help is one -h away)."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f'{self.prog}: {message} (see {self.prog} -h)\n')


def _common(timeout_s: float) -> argparse.ArgumentParser:
    p = Parser(add_help=False)
    p.add_argument('--timeout', type=float, default=timeout_s, metavar='S',
                   help='how long to wait for the answer or the result [s] '
                   f'(default {timeout_s:g})')
    p.add_argument('--discovery-timeout', type=float, default=5.0, metavar='S',
                   help='how long to look for the drive on the ROS graph [s] (default 5)')
    return p


def build_parser(scan_vendors: bool = True) -> argparse.ArgumentParser:
    """The parser of every command; `scan <key>` for each vendor only with `scan_vendors`."""
    ap = Parser(
        prog=PROG, description='Operate stepper drives through their ROS nodes, or scan a bus '
        'for drives.', epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='command', metavar='COMMAND', required=True)
    quick, slow = _common(10.0), _common(120.0)

    p = sub.add_parser('list', parents=[quick], help='drives on the ROS graph with their state')
    p.add_argument('--json', action='store_true', help='print JSON instead of a table')

    p = sub.add_parser('status', parents=[quick], help='live status table (Ctrl-C ends)')
    p.add_argument('drives', nargs='*', metavar='DRIVE', help='drives to show (default: all)')
    p.add_argument('--once', action='store_true', help='print one snapshot and exit (exit 5 '
                   'if a drive shown is in fault)')
    p.add_argument('--period', type=float, default=0.5, metavar='S',
                   help='refresh period [s] (default 0.5)')
    p.add_argument('--duration', type=float, default=0.0, metavar='S',
                   help='end after this long [s] (default: until Ctrl-C)')

    for name, text in (('enable', 'switch the power stage on (target = actual position first)'),
                       ('disable', 'switch the power stage off'),
                       ('stop', 'controlled stop with the profile deceleration'),
                       ('fault-reset', 'clear the faults the drive allows to clear'),
                       ('save', "store the drive's parameters in its non-volatile memory")):
        p = sub.add_parser(name, parents=[quick], help=text)
        p.add_argument('drive', metavar='DRIVE')

    p = sub.add_parser('home', parents=[slow], help='run the configured homing and wait for it')
    p.add_argument('drive', metavar='DRIVE')

    p = sub.add_parser('move', parents=[slow],
                       help='move to a position (joint units: rad or m) and wait, with progress')
    p.add_argument('drive', metavar='DRIVE')
    p.add_argument('position', type=float, metavar='POSITION')

    p = sub.add_parser('jog', parents=[quick],
                       help='run at a velocity for a duration, then stop')
    p.add_argument('drive', metavar='DRIVE')
    p.add_argument('velocity', type=float, metavar='VELOCITY', help='joint units/s')
    p.add_argument('duration', type=float, metavar='DURATION', help='seconds')
    p.add_argument('--no-stop', action='store_true',
                   help="do not call stop at the end: the node's velocity watchdog stops the "
                   'drive (command_timeout_s after the last command)')

    p = sub.add_parser('read', parents=[quick], help="read a raw register in the drive's own "
                       'addressing (Modbus register, 0xINDEX:SUB, X-MIND K code)')
    p.add_argument('drive', metavar='DRIVE')
    p.add_argument('address', metavar='ADDRESS')
    p.add_argument('type', nargs='?', default='u16', metavar='TYPE',
                   help='u8 i8 u16 i16 u32 i32 u64 i64 or string (default u16)')

    p = sub.add_parser('write', parents=[quick], help='write a raw register (the node needs '
                       'allow_raw_write: true)')
    p.add_argument('drive', metavar='DRIVE')
    p.add_argument('address', metavar='ADDRESS')
    p.add_argument('type', metavar='TYPE')
    p.add_argument('value', metavar='VALUE', help='integer (decimal or 0x hex), or text')

    _scan_parser(sub, scan_vendors)
    return ap


def _scan_parser(sub, with_vendors: bool) -> None:
    scan = sub.add_parser('scan', help='find the drives on a bus (talks to the bus directly: '
                          'stop the node of that bus first)')
    if not with_vendors:
        return
    vendors = scan.add_subparsers(dest='vendor', metavar='VENDOR', required=True)

    def common(p, timeout_s: float, max_time_s: float) -> None:
        p.add_argument('--timeout', type=float, default=timeout_s, metavar='S',
                       help=f'answer timeout per address [s] (default {timeout_s:g})')
        p.add_argument('--max-time', type=float, default=max_time_s, metavar='S',
                       help=f'the whole scan ends after this long [s] (default {max_time_s:g})')
        p.add_argument('--write-yaml', metavar='FILE',
                       help='write a params file that starts the node for the drives found')
        p.add_argument('--node-name', metavar='NAME',
                       help='node name in that file (default <vendor>_node)')

    from .scan import scanners  # as main() imports it: for scan command lines only
    for key, scanner in scanners().items():
        p = vendors.add_parser(key, help=scanner.help)
        common(p, *scanner.add_options(p))


def _command(argv: list[str]) -> str | None:
    """The command word of a command line (the top-level parser has no option with a value)."""
    return next((a for a in argv if not a.startswith('-')), None)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format=f'{PROG}: %(message)s')
    # `scan <key>` comes from the vendor modules (VENDOR.scanner); loading them takes about a
    # third of a second (canopen, pymodbus), so only a scan command line pays it
    parser = build_parser(scan_vendors=_command(argv) == 'scan')
    args = parser.parse_args(argv)
    try:
        if args.command == 'scan':
            from . import scan
            return scan.run(args)
        if getattr(args, 'timeout', 1.0) <= 0:
            raise CliError(EXIT_USAGE, '--timeout must be > 0')
        from . import ros_commands
        return ros_commands.run(args)
    except CliError as e:
        print(f'{PROG}: {e.message}', file=sys.stderr, flush=True)
        logger.debug('exit %d (%s)', e.code, EXIT_NAMES.get(e.code, '?'))
        return e.code
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED


def stepperctl() -> None:
    """The stepperctl executable (console script in setup.py)."""
    sys.exit(main())


if __name__ == '__main__':
    sys.exit(main())
