"""What the serial links (modbus_rtu.ModbusRtuBus, ascii_line.AsciiLine) set on a port they
have just opened with pyserial. No ROS.

Low latency: a USB serial adapter with an FTDI chip sends what it received to the host when its
buffer fills or its latency timer (16 ms by default) runs out, so every short reply waits up to
16 ms: at 19200 baud that nearly doubles an RD4 transaction. pyserial's
`Serial.set_low_latency_mode(True)` (Linux) sets the tty's ASYNC_LOW_LATENCY flag, which the
ftdi_sio driver turns into a latency timer of 1 ms (linux drivers/usb/serial/ftdi_sio.c,
write_latency_timer); ports without it (a pty, an on-board UART, a pyserial URL) refuse or lack
the call, and that is fine. Where the port is a USB serial device whose latency timer stays
above 1 ms (the call refused, or a driver that ignores the flag) the link logs one warning
naming the timer's sysfs file and how to set it.

RS-485 mode (`rs485: true`): for a UART whose RS-485 transceiver takes its direction from RTS
and has no automatic direction control, the kernel's RS-485 mode (TIOCSRS485, set through
pyserial's `rs485_mode` with `serial.rs485.RS485Settings`) raises RTS while it sends and drops
it after the last stop bit. A serial driver without RS-485 support refuses it: the link does not
open, with one line naming the parameter. Most USB-RS485 converters (FTDI, CH340 ...) switch
direction by themselves and need `rs485: false`.
"""

from __future__ import annotations

import logging
import os
from typing import Any

logger = logging.getLogger(__name__)

# One directory per USB serial port (ttyUSBn), with the latency_timer attribute for ftdi_sio.
USB_SERIAL_DEVICES = '/sys/bus/usb-serial/devices'
_warned: set[str] = set()          # latency_timer files warned about (once per process)
# The `rs485` bus parameter of the RS-485 vendors (RD4, X-MIND K).
RS485_DESCRIPTION = ("the serial driver's RS-485 mode: RTS high while sending, for a UART or "
                     'adapter whose transceiver takes its direction from RTS (no automatic '
                     'direction control); most USB-RS485 converters (FTDI, CH340) switch by '
                     'themselves: false')


class PortSetupError(Exception):
    """The port refused a setting the parameters ask for; str() is one line naming it."""


def latency_timer_file(device: str) -> str | None:
    """The sysfs latency_timer of a USB serial port (a symlink such as /dev/serial/by-id/...
    resolved to its ttyUSBn), or None for any other port."""
    path = os.path.join(USB_SERIAL_DEVICES, os.path.basename(os.path.realpath(device)),
                        'latency_timer')
    return path if os.path.isfile(path) else None


def _read_ms(path: str) -> int | None:
    try:
        with open(path, encoding='ascii') as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def set_low_latency(port: Any, device: str) -> None:
    """Ask for low-latency mode; one warning (per timer file and process) where a USB serial
    port's latency timer stays above 1 ms."""
    try:
        port.set_low_latency_mode(True)
        refused = ''
    except (AttributeError, NotImplementedError, ValueError, OSError) as e:
        refused = str(e) or type(e).__name__       # a pty, a URL, another OS
    timer = latency_timer_file(device)
    if timer is None:
        if refused:
            logger.debug('%s: no low-latency mode (%s)', device, refused)
        return
    ms = _read_ms(timer)
    if (ms is not None and ms <= 1) or timer in _warned:
        return
    _warned.add(timer)
    logger.warning(
        '%s: the USB adapter holds every reply for its latency timer (%s ms) and low-latency '
        'mode could not be set (%s): set it to 1 ms with `echo 1 > %s` as root, or for good '
        'with a udev rule (docs/troubleshooting.md)', device, '?' if ms is None else ms,
        refused or 'the driver kept the timer', timer)


def set_rs485(port: Any, device: str) -> None:
    """The kernel's RS-485 mode: RTS high while sending, low after (PortSetupError when the
    port's driver refuses it)."""
    from serial.rs485 import RS485Settings
    try:
        port.rs485_mode = RS485Settings(rts_level_for_tx=True, rts_level_for_rx=False)
    except (NotImplementedError, ValueError, OSError) as e:
        raise PortSetupError(
            f'parameter rs485: true, but {device} refuses RS-485 mode ({e}); it needs a serial '
            'driver with RS-485 support (RTS direction control); an adapter that switches '
            'direction by itself needs rs485: false') from None


def prepare(port: Any, device: str, *, rs485: bool = False) -> None:
    """Everything a link sets after opening `port` (`device` = its path or URL)."""
    set_low_latency(port, device)
    if rs485:
        set_rs485(port, device)
