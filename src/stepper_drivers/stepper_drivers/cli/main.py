"""stepperctl: command line entry point (argument parsing, exit codes, one-line errors)."""

from __future__ import annotations

import argparse
import logging
import sys

from .. import vendor_table
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


def build_parser() -> argparse.ArgumentParser:
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

    _scan_parser(sub)
    return ap


def _rd4_scan_options(p) -> tuple[float, float]:
    p.add_argument('--port', required=True, help='serial device or pyserial URL')
    p.add_argument('--ids', default='1-247', help='unit ids, e.g. 1-10,12 (default 1-247)')
    p.add_argument('--baudrate', default='9600,19200', help='baud rates to try, in order '
                   '(default 9600,19200)')
    p.add_argument('--parity', default='E,N,O', help='parities to try, in order (default '
                   'E,N,O; factory setting 9600 8E1)')
    p.add_argument('--all-settings', action='store_true',
                   help='go on with the other settings after one found drives')
    return 0.05, 120.0


def _xplus_mt_scan_options(p) -> tuple[float, float]:
    p.add_argument('--host', action='append', default=None,
                   help='host, range 192.168.1.10-20 or network 192.168.1.0/28; repeatable '
                   '(default 192.168.1.10, the factory address)')
    p.add_argument('--port', type=int, default=502, help='TCP port (default 502)')
    p.add_argument('--ids', default='1-247', help='unit ids (default 1-247)')
    return 0.2, 60.0


def _xmind_k_scan_options(p) -> tuple[float, float]:
    p.add_argument('--port', required=True, help='serial device or pyserial URL')
    p.add_argument('--addresses', default='0-47', help='addresses (default 0-47)')
    p.add_argument('--answer-delay-ms', type=float, default=10.0, metavar='MS',
                   help='answer delay preset RD the drives use (§4.2.2.5, factory 10)')
    p.add_argument('--local-echo', action='store_true',
                   help='the RS-485 adapter echoes what it sends')
    return 0.03, 30.0


def _vector_step_scan_options(p) -> tuple[float, float]:
    p.add_argument('--interface', default='socketcand',
                   help='python-can interface: socketcan (Linux CAN card) or socketcand '
                   '(default, the loopback broker)')
    p.add_argument('--channel', default='can0', help='CAN channel (default can0)')
    p.add_argument('--bitrate', type=int, default=125000, help='bit rate (default 125000)')
    p.add_argument('--can-host', default='127.0.0.1', help='socketcand host')
    p.add_argument('--can-port', type=int, default=29536, help='socketcand port')
    p.add_argument('--ids', default='1-127', help='node-ids (default 1-127)')
    p.add_argument('--listen', type=float, default=0.5, metavar='S',
                   help='how long to collect answers to the broadcast probe [s]')
    return 0.3, 30.0


# The options of `stepperctl scan <key>` for each vendor of the table with a scanner (scan_help);
# each returns its (answer timeout per address, whole scan) defaults [s].
SCAN_OPTIONS = {'rd4': _rd4_scan_options, 'xplus_mt': _xplus_mt_scan_options,
                'xmind_k': _xmind_k_scan_options, 'vector_step': _vector_step_scan_options}


def _scan_parser(sub) -> None:
    scan = sub.add_parser('scan', help='find the drives on a bus (talks to the bus directly: '
                          'stop the node of that bus first)')
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

    for row in vendor_table.ROWS:
        if row.scan_help:
            p = vendors.add_parser(row.key, help=row.scan_help)
            common(p, *SCAN_OPTIONS[row.key](p))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format=f'{PROG}: %(message)s')
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == 'scan':
            from . import scan
            if args.vendor == 'xplus_mt' and not args.host:
                args.host = ['192.168.1.10']
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


if __name__ == '__main__':
    sys.exit(main())
