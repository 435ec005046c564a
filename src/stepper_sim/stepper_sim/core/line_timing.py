"""Serial line timing for simulators (no rclpy): character and frame times, Modbus RTU t3.5.

A pty delivers bytes at once whatever baud rate it claims (research/transports.md §C), so a
serial simulator that should look like a real line delays its reply with `LineTiming`: the time
the request takes on the wire, the silent interval, and the reply's own transmission time.
`LineTiming(enabled=False)` gives zero delays (the default of the simulators: fast tests).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time

logger = logging.getLogger(__name__)

# Modbus over Serial Line V1.02 §2.5.1.1: above 19200 baud use fixed 750 us (t1.5) and 1.750 ms
# (t3.5) instead of character times.
FIXED_T15_S = 0.000750
FIXED_T35_S = 0.001750
FIXED_ABOVE_BAUD = 19200


def char_time_s(baud: int, bits_per_char: int = 11) -> float:
    """One character on the line: start bit + data + parity + stop bits (RTU: 11 bits)."""
    if baud <= 0:
        raise ValueError(f'baud must be > 0, got {baud}')
    return bits_per_char / baud


def frame_time_s(n_bytes: int, baud: int, bits_per_char: int = 11) -> float:
    return n_bytes * char_time_s(baud, bits_per_char)


def t35_s(baud: int, bits_per_char: int = 11) -> float:
    """Inter-frame silence: 3.5 character times, fixed 1.75 ms above 19200 baud."""
    if baud > FIXED_ABOVE_BAUD:
        return FIXED_T35_S
    return 3.5 * char_time_s(baud, bits_per_char)


def t15_s(baud: int, bits_per_char: int = 11) -> float:
    """Maximum silence inside a frame: 1.5 character times, fixed 0.75 ms above 19200 baud."""
    if baud > FIXED_ABOVE_BAUD:
        return FIXED_T15_S
    return 1.5 * char_time_s(baud, bits_per_char)


@dataclasses.dataclass
class LineTiming:
    """Delay of a reply as a real line delivers it; all zero when not enabled.

    reply_delay_s = request on the wire + t3.5 + turnaround_s + reply on the wire: the time from
    the master's last byte written (a pty takes it at once) to the reply's last byte arriving.
    """

    baud: int = 19200
    bits_per_char: int = 11
    enabled: bool = False
    turnaround_s: float = 0.0

    def reply_delay_s(self, request_bytes: int, reply_bytes: int) -> float:
        if not self.enabled:
            return 0.0
        return (frame_time_s(request_bytes, self.baud, self.bits_per_char)
                + t35_s(self.baud, self.bits_per_char) + self.turnaround_s
                + frame_time_s(reply_bytes, self.baud, self.bits_per_char))

    def wait_before_reply(self, request_bytes: int, reply_bytes: int,
                          since_s: float | None = None) -> None:
        """Block until the reply is due (since_s: monotonic time the request was complete)."""
        delay = self.reply_delay_s(request_bytes, reply_bytes)
        if delay > 0.0:
            start = time.monotonic() if since_s is None else since_s
            remaining = start + delay - time.monotonic()
            if remaining > 0.0:
                time.sleep(remaining)   # a rate, not synchronisation: the line's own speed

    async def async_wait_before_reply(self, request_bytes: int, reply_bytes: int,
                                      since_s: float | None = None) -> None:
        delay = self.reply_delay_s(request_bytes, reply_bytes)
        if delay > 0.0:
            start = time.monotonic() if since_s is None else since_s
            remaining = start + delay - time.monotonic()
            if remaining > 0.0:
                await asyncio.sleep(remaining)
