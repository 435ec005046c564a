"""Text rendering of drive status: the status table (stepperctl status, the demo) and progress.

Works on anything shaped like stepper_drivers_msgs/DriveStatus; no rclpy import.
"""

from __future__ import annotations

import math
import sys
from typing import Any, Iterable, Sequence

# Older than this, a status row is marked stale (the node publishes at publish_rate_hz >= 0.1).
STALE_AFTER_S = 2.0
CLEAR_SCREEN = '\x1b[H\x1b[2J'

# 120 columns: DRIVE fits 'vector_step_node/axis1', STATE fits 'NOT READY TO SWITCH ON'.
COLUMNS = (('DRIVE', 22, '<'), ('ADDR', 4, '>'), ('STATE', 22, '<'), ('POSITION', 10, '>'),
           ('VELOCITY', 9, '>'), ('FLAGS', 5, '<'), ('FAULT / ALARMS', 27, '<'),
           ('LINK tx/err/rc', 14, '>'))
FLAGS_LEGEND = ('FLAGS: E enabled, M moving, T target reached, H homed, ~ position estimated; '
                'LINK: transactions/errors/reconnects')


def flags(m: Any) -> str:
    return ''.join(c if on else '.' for c, on in (
        ('E', m.enabled), ('M', m.moving), ('T', m.target_reached), ('H', m.homed),
        ('~', m.position_estimated)))


def fault_text(m: Any) -> str:
    if m.fault:
        return f'0x{m.fault_code:04X} {m.fault_text}'.strip()
    if len(m.alarms):
        return '; '.join(m.alarms)
    if m.last_refusal:
        return f'refused: {m.last_refusal}'
    return '-'


def number(value: float, width: int, decimals: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return 'n/a'.rjust(width)
    return f'{value:+.{decimals}f}'


def _cell(text: str, width: int, align: str) -> str:
    text = str(text)
    if len(text) > width:
        text = text[:width - 1] + '…'
    return f'{text:{align}{width}}'


def row(label: str, m: Any | None, age_s: float) -> list[str]:
    if m is None:
        return [label, '', 'NO STATUS YET', '', '', '', '', '']
    state = m.state if age_s <= STALE_AFTER_S else f'STALE ({age_s:.0f} s) {m.state}'
    velocity = m.velocity if m.velocity_valid else float('nan')
    return [label, m.address, state, number(m.position, 10), number(velocity, 9, 2),
            flags(m), fault_text(m),
            f'{m.link_transactions}/{m.link_errors}/{m.link_reconnects}']


def table(rows: Iterable[Sequence[str]], legend: bool = True) -> str:
    head = ' '.join(_cell(name, w, a) for name, w, a in COLUMNS)
    lines = [head.rstrip(), '-' * len(head)]
    for r in rows:
        lines.append(' '.join(_cell(text, w, a) for text, (_n, w, a) in zip(r, COLUMNS)).rstrip())
    if legend:
        lines.append(FLAGS_LEGEND)
    return '\n'.join(lines)


def progress_bar(fraction: float, width: int = 30) -> str:
    fraction = min(max(fraction, 0.0), 1.0)
    full = int(round(fraction * width))
    return '[' + '#' * full + '-' * (width - full) + f'] {fraction * 100:3.0f}%'


class Live:
    """Redraws in place on a terminal; prints a line at most every `period_s` elsewhere."""

    def __init__(self, stream=None, period_s: float = 1.0):
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty()
        self.period_s = period_s
        self._last = -math.inf
        self._width = 0

    def line(self, text: str, now: float, force: bool = False) -> None:
        if self.tty:
            pad = max(self._width - len(text), 0)
            self.stream.write('\r' + text + ' ' * pad)
            self._width = len(text)
            self.stream.flush()
        elif force or now - self._last >= self.period_s:
            self.stream.write(text + '\n')
            self.stream.flush()
            self._last = now

    def end(self) -> None:
        if self.tty and self._width:
            self.stream.write('\n')
            self.stream.flush()
            self._width = 0
