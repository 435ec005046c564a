"""What the bus scanners share: `Scanner` (a vendor's `stepperctl scan <key>`), the results they
return, their time bound, progress line, address parsing and errors (no rclpy here).

A vendor with a scanner defines it in vendors/<key>_scan.py and sets it as `scanner` of its
drive.Vendor; the command itself (options common to every scanner, the params file it writes,
exit codes) is cli/scan.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import sys
import time
from typing import Any, Callable, Iterable, Iterator, TypeVar

T = TypeVar('T')


class ScanError(Exception):
    """Ends a scan: the bus cannot be scanned (a missing port, no broker); the message is one
    line. stepperctl exits 1 (failed)."""


class ScanUsageError(ScanError):
    """An option's value the scanner cannot use; stepperctl exits 2 (usage)."""


@dataclasses.dataclass
class Found:
    """One drive that answered: its address, identity and what its params file needs."""

    address: int
    identity: dict[str, str]
    drive_params: dict[str, Any] = dataclasses.field(default_factory=dict)
    notes: list[str] = dataclasses.field(default_factory=list)   # comments in the YAML
    raw: dict[str, int] = dataclasses.field(default_factory=dict)  # values read, for the bus


@dataclasses.dataclass
class BusResult:
    """The drives found on one bus (one serial setting, one TCP host, one CAN bus)."""

    vendor: str
    description: str
    bus_params: dict[str, Any]
    drives: list[Found] = dataclasses.field(default_factory=list)
    header: list[str] = dataclasses.field(default_factory=list)  # comments at the top


class Deadline:
    def __init__(self, max_time_s: float):
        self.max_time_s = max_time_s
        self.end = time.monotonic() + max_time_s
        self.hit = False

    def over(self) -> bool:
        if time.monotonic() >= self.end:
            self.hit = True
        return self.hit

    def each(self, items: Iterable[T]) -> Iterator[T]:
        """`items` in turn, each only while the deadline is not over."""
        for item in items:
            if self.over():
                return
            yield item


@dataclasses.dataclass(frozen=True)
class Scanner:
    """`stepperctl scan <key>` of one vendor (drive.Vendor.scanner)."""

    help: str      # the help line of `stepperctl scan <key>`
    hint: str      # what to check when the scan finds nothing
    # Adds the vendor's options to the `scan <key>` parser; returns its defaults [s] for the
    # answer timeout per address (--timeout) and the whole scan (--max-time).
    add_options: Callable[[argparse.ArgumentParser], tuple[float, float]]
    # Probes the bus the parsed options name until done or the deadline is over: the drives
    # found, one BusResult per bus (none: nothing answered). Raises ScanError.
    scan: Callable[[argparse.Namespace, Deadline], list[BusResult]]


class Progress:
    """A redrawn line on a terminal, elsewhere a line per 10 %; on stderr (not mixed with the
    results)."""

    def __init__(self, what: str, total: int, stream=None):
        self.what, self.total = what, max(total, 1)
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.done = 0
        self.found = 0
        self._shown = -1
        self.t0 = time.monotonic()

    def step(self, label: str, found: int | None = None) -> None:
        self.done += 1
        if found is not None:
            self.found = found
        pct = int(100 * self.done / self.total)
        text = (f'scan {self.what}: {label:<14} {self.done}/{self.total} ({pct:3d} %), '
                f'found {self.found}, {time.monotonic() - self.t0:4.1f} s')
        if self.tty:
            self.stream.write('\r' + text)
            self.stream.flush()
        elif pct // 10 != self._shown or self.done == self.total:
            self._shown = pct // 10
            self.stream.write(text + '\n')
            self.stream.flush()

    def end(self) -> None:
        if self.tty:
            self.stream.write('\n')
            self.stream.flush()


def parse_ids(text: str, lo: int, hi: int, what: str) -> list[int]:
    """'1-10,12,0x20' -> [1..10, 12, 32], each within lo..hi."""
    ids: list[int] = []
    try:
        for part in text.split(','):
            part = part.strip()
            if not part:
                continue
            if '-' in part[1:]:
                a, b = part.split('-', 1) if not part.startswith('-') else ('-', part)
                first, last = int(a, 0), int(b, 0)
            else:
                first = last = int(part, 0)
            if first > last:
                first, last = last, first
            ids.extend(range(first, last + 1))
    except ValueError:
        raise ScanUsageError(f'{what}: {text!r} is not a list of numbers and ranges '
                             '(e.g. 1-10,12)') from None
    bad = [i for i in ids if not lo <= i <= hi]
    if bad or not ids:
        raise ScanUsageError(f'{what}: {text!r} (allowed: {lo}..{hi})')
    return sorted(set(ids))


def parse_hosts(specs: Iterable[str]) -> list[str]:
    """'192.168.1.10', '192.168.1.10-20', '10.0.0.0/30', 'localhost' -> host list."""
    hosts: list[str] = []
    for spec in specs:
        for part in spec.split(','):
            part = part.strip()
            if not part:
                continue
            try:
                if '/' in part:
                    net = ipaddress.ip_network(part, strict=False)
                    hosts.extend(str(h) for h in (net.hosts() if net.num_addresses > 2 else net))
                elif '-' in part and part.count('.') == 3:
                    base, last = part.rsplit('-', 1)
                    first_ip = ipaddress.ip_address(base)
                    prefix = base.rsplit('.', 1)[0]
                    for n in range(int(str(first_ip).rsplit('.', 1)[1]), int(last) + 1):
                        hosts.append(f'{prefix}.{n}')
                else:
                    hosts.append(part)
            except ValueError:
                raise ScanUsageError(f'--host: {part!r} is not a host, a range '
                                     '(192.168.1.10-20) or a network (192.168.1.0/28)') from None
    if len(hosts) > 1024:
        raise ScanUsageError(f'--host: {len(hosts)} hosts; scan at most 1024 at once')
    return hosts
