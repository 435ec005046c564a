"""stepperctl scan: find the drives that answer on a bus, without a node (no rclpy here).

Each vendor's scanner is the `scanner` of its drive.Vendor (vendors/<key>_scan.py: what it
probes, per the vendor's manual); it probes one address at a time through the project's own
protocol code, so what the scanner finds the node can reach the same way.

Every scan is bounded by --max-time; progress goes to stderr. `--write-yaml FILE` writes a params
file that starts the vendor's node for the drives found (one drive block per address).
"""

from __future__ import annotations

import importlib
import sys
import time
from typing import Any

from ..contract.scanning import BusResult, Deadline, ScanError, Scanner, ScanUsageError
from ..vendors import table as vendor_table
from .errors import EXIT_FAILED, EXIT_NOT_FOUND, EXIT_OK, EXIT_USAGE, CliError

NODE_NAMES = {row.key: row.node for row in vendor_table.ROWS}
ADDRESS_NAMES = {row.key: row.address_param for row in vendor_table.ROWS}


def scanner(key: str) -> Scanner | None:
    """The scanner of the table's vendor `key` (its vendor module's VENDOR.scanner)."""
    return importlib.import_module(vendor_table.BY_KEY[key].module).VENDOR.scanner


def scanners() -> dict[str, Scanner]:
    """{key: scanner} of every vendor of the table that has one, in the table's order."""
    found = {row.key: scanner(row.key) for row in vendor_table.ROWS}
    return {key: s for key, s in found.items() if s is not None}


# --------------------------------------------------------------------------------- YAML out
YAML_WORDS = ('N', 'Y', 'YES', 'NO', 'ON', 'OFF', 'TRUE', 'FALSE', 'NULL', '~')


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    text = str(value)
    # Quote what YAML would read as something else: N (false!), numbers, '', special starts.
    if text == '' or text.upper() in YAML_WORDS or _looks_numeric(text) or ': ' in text \
            or text.endswith(':') or text[0] in '#*&![]{}|>\'"%@`,?-':
        return "'" + text.replace("'", "''") + "'"
    return text


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def drive_name(vendor: str, address: int) -> str:
    return f'axis{address}'


def render_yaml(result: BusResult, node_name: str | None = None, command: str = '') -> str:
    """A params file for one bus: node name key, ros__parameters, drives and drives.<name>."""
    node_name = node_name or NODE_NAMES[result.vendor]
    lines = [f'# Written by stepperctl scan {result.vendor} on {time.strftime("%Y-%m-%d %H:%M")}'
             + (f' ({command})' if command else '') + '.']
    lines += [f'# {h}' for h in result.header]
    lines += ['# Limits and profiles are the defaults: set min/max_position, max_velocity and the',
              '# profile for the machine before moving it (docs/interface.md lists every '
              'parameter).',
              f'{node_name}:', '  ros__parameters:']
    for key, value in result.bus_params.items():
        lines.append(f'    {key}: {_yaml_scalar(value)}')
    names = [drive_name(result.vendor, d.address) for d in result.drives]
    lines.append(f'    drives: [{", ".join(names)}]')
    for name, d in zip(names, result.drives):
        lines.append(f'    drives.{name}:')
        for k, v in d.identity.items():
            lines.append(f'      # {k}: {v}')
        for note in d.notes:
            lines.append(f'      # {note}')
        params = {ADDRESS_NAMES[result.vendor]: d.address, 'joint_name': f'joint{d.address}',
                  **d.drive_params}
        for key, value in params.items():
            if isinstance(value, dict):
                lines.append(f'      {key}:')
                for k2, v2 in value.items():
                    lines.append(f'        {k2}: {_yaml_scalar(v2)}')
            else:
                lines.append(f'      {key}: {_yaml_scalar(value)}')
    return '\n'.join(lines) + '\n'


def yaml_paths(path: str, results: list[BusResult]) -> list[str]:
    """One file per bus: FILE for the first, FILE with _2, _3 ... before the suffix after."""
    out = []
    for i, _ in enumerate(results):
        if i == 0:
            out.append(path)
        else:
            stem, dot, ext = path.rpartition('.')
            out.append(f'{stem}_{i + 1}.{ext}' if dot else f'{path}_{i + 1}')
    return out


# ----------------------------------------------------------------------------------- output
def print_results(results: list[BusResult]) -> None:
    for r in results:
        print(f'{r.description}: {len(r.drives)} drive(s)')
        for d in r.drives:
            ident = ', '.join(f'{k}={v}' for k, v in d.identity.items())
            print(f'  {ADDRESS_NAMES[r.vendor]} {d.address:>3}: {ident}')
            for note in d.notes:
                print(f'      note: {note}')
    sys.stdout.flush()


def run(args) -> int:
    scan = scanner(args.vendor)
    deadline = Deadline(args.max_time)
    try:
        results = scan.scan(args, deadline)
    except ScanUsageError as e:
        raise CliError(EXIT_USAGE, str(e)) from None
    except ScanError as e:
        raise CliError(EXIT_FAILED, str(e)) from None
    if deadline.hit:
        print(f'scan {args.vendor}: stopped after --max-time {args.max_time:g} s; not every '
              'address was probed', file=sys.stderr)
    if not results:
        raise CliError(EXIT_NOT_FOUND, f'scan {args.vendor}: no drive answered; '
                       + scan.hint)
    print_results(results)
    if args.write_yaml:
        command = ' '.join(sys.argv[1:]) if sys.argv else ''
        for path, r in zip(yaml_paths(args.write_yaml, results), results):
            with open(path, 'w', encoding='utf-8') as f:
                f.write(render_yaml(r, args.node_name, command))
            print(f'wrote {path}: start the node with  ros2 run stepper_drivers '
                  f'{NODE_NAMES[r.vendor]} --ros-args --params-file {path}'
                  + (f' -r __node:={args.node_name}' if args.node_name else ''))
    return EXIT_OK
