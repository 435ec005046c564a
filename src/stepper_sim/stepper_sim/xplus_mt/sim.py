"""Simulated R.T.A. X-PLUS MT drives on Modbus TCP (pymodbus 3.16 server), and `main()`.

Behaviour from the manual (`shared/manuals/rta_xplus_mt_modbus_tcp.txt`; "§12" etc. are its
chapters, "T13" its tables, "A<n>" the ambiguities of `shared/spec/xplus_mt.md` §11):
- holding registers of `xplus_mt_map` on FC 03/04/06/10; several drives by unit id on one port
  (unknown unit ids: exception 0x0B); exceptions per spec §1.3 (strict): 0x01 any other function
  code (whatever its address), 0x02 unmapped address or write to a read-only register, 0x03
  value out of range, a quantity outside the Modbus limits (FC03/04 1..125, FC16 1..123) or a
  malformed request (Modbus Application Protocol v1.1b3 §6.3, §7);
- 32-bit values in the word order of register 1162; a pair commits when its second (higher
  address) word is written, FC06 on the first word stays pending (§11 "Data Format", A2);
- the CiA 402 state machine of T13/T14 evaluated on controlword levels (A4): power-on SWITCH ON
  DISABLED, HV "present >= 500 ms" for Switch On (§12 transition 3), quick stop option code 5
  (§12 transition 16), statusword values of spec §3.5 (0x0270, 0x0231, 0x0233, 0x0637 ...);
- profile position (bit 4 edge, set-point acknowledge, abs/rel bit 6, change set immediately bit 5
  with multi-set-point rules, halt bit 8), profile velocity (signed Target Velocity, A8/A10),
  homing methods 3-6, 19-22, 35, 37 (§13 "Homing Mode") on a simulated axis (`axis.py`);
- faults with the 1007 codes and the alarm log 1220-1239, fault reset only without the cause,
  save 0x6173/0x1111 to 1260 (a JSON file per unit in storage_dir), restore 0x6F6C to 1261, the
  1097 watchdog (§13 "Register 1097": no read or write request for this unit within the timeout
  -> Fault, current off; time the simulator itself was not running does not count).
Link faults go through a `FaultyTcpProxy` in front of the pymodbus server.

This module is the Modbus TCP front (request decoding, exceptions, units, the server thread, the
ROS executable); each drive behind it is an `xplus_mt_device.XplusMtDriveSim`, whose CiA 402 is the
shared device-side `cia402_device`.

Non-ROS API: `XplusMtSim(...).start()`, `.port`, `.drives[name]`, `.inject_fault()`, `.stop()`.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import sys
import threading
import time
from typing import Callable, Sequence

from pymodbus.constants import ExcCodes
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from stepper_drivers.vendors.xplus_mt import regmap as xm

from ..core.faults import LATE_REPLY, OK, FaultyTcpProxy, LinkFaults, garble_one
from .device import LOST_REPLY_HOLD_S, XplusMtDriveConfig, XplusMtDriveSim

__all__ = ['XplusMtDriveSim', 'XplusMtDriveConfig', 'XplusMtSim', 'build', 'main']

logger = logging.getLogger(__name__)
SHUTDOWN_STEP_S = 3.0    # each of the server thread's shutdown steps (the caller joins 10 s)
REGISTER_BLOCK = (1000, 270)    # 1000..1269: the manual's whole address range (spec §2.8)
LINK_KINDS = ('no_reply', 'late_reply', 'corrupt_reply', 'cut', 'link_ok')
DRIVE_KINDS = ('drive_fault', 'clear_fault', 'hv_off', 'hv_on', 'lose_write_reply')
# 'lose_write_reply': the next write of register `code` whose word has every bit of `value`
# set takes effect, but its reply is held LOST_REPLY_HOLD_S: lost to a master with a shorter
# timeout


async def _bounded(step, what: str) -> None:
    try:
        await asyncio.wait_for(step, SHUTDOWN_STEP_S)
    except asyncio.TimeoutError:
        logger.warning('%s did not stop within %g s; leaving it to process exit', what,
                       SHUTDOWN_STEP_S)


class _Refusal(ModbusPDU):
    """A request answered by an exception without touching the device model."""

    def __init__(self, function_code: int, exception_code: ExcCodes):
        super().__init__()
        self.function_code = function_code
        self.exception_code_to_send = exception_code

    async def datastore_update(self, context, device_id) -> ModbusPDU:
        return ExceptionResponse(self.function_code, self.exception_code_to_send)


class _XplusMtDecoder(DecodePDU):
    """Request decoding as the drive answers it (spec §1.3; Modbus Application Protocol v1.1b3
    §6.3/§6.4/§6.12, §7). pymodbus alone serves FC 01/02/05/07/08/0F/11/2B as a generic device
    (FC07 and FC08 even answer normally) and replies `80 01` (function code 0, not an exception
    reply of the request's function) when it cannot decode a request, e.g. FC03 with quantity 0
    or 126."""

    FUNCTION_CODES = (3, 4, 6, 16)     # §11 "Supported Function Code"

    def __init__(self):
        super().__init__(True)

    def decode(self, frame: bytes) -> ModbusPDU | None:
        if not frame:
            return None
        function_code = frame[0]
        if function_code not in self.FUNCTION_CODES:
            return _Refusal(function_code & 0x7F, ExcCodes.ILLEGAL_FUNCTION)
        if function_code in (3, 4) and not (   # pymodbus would fail to decode these
                len(frame) >= 5 and 1 <= int.from_bytes(frame[3:5], 'big') <= 125):
            return _Refusal(function_code, ExcCodes.ILLEGAL_VALUE)
        # FC16's quantity (1..123) and byte count reach pymodbus's own check (0x03) already
        return super().decode(frame) or _Refusal(function_code, ExcCodes.ILLEGAL_VALUE)


class XplusMtSim:
    """One Modbus TCP port (127.0.0.1) with one or more simulated X-PLUS MT drives.

    A `sim_node.SimBackend`. Start with start() (returns once listening; `.port` is then the
    bound port), stop with stop(). `.drives[name]` is the XplusMtDriveSim (its `.axis`, exact
    `.true_position_steps`, `.statusword`, `.register(name)`).
    """

    def __init__(self, host: str = '127.0.0.1', port: int = 0,
                 drives: Sequence[XplusMtDriveConfig] | None = None, word_order: str = 'little',
                 line_timing: bool = False, storage_dir: str | None = None, *,
                 strict: bool = True, reply_latency_s: float = 0.002, tick_s: float = 0.02,
                 clock: Callable[[], float] = time.monotonic):
        if host not in ('127.0.0.1', 'localhost'):
            raise ValueError(f'host {host!r}: simulators bind to 127.0.0.1 only')
        if word_order not in xm.WORD_ORDERS:
            raise ValueError(f'word_order {word_order!r}; allowed: little, big')
        drives = list(drives) if drives else [XplusMtDriveConfig('axis1')]
        units = [d.unit_id for d in drives]
        if len(set(units)) != len(units):
            raise ValueError(f'unit ids must be unique, got {units}')
        if len({d.name for d in drives}) != len(drives):
            raise ValueError('drive names must be unique')
        self.host = '127.0.0.1'
        self.requested_port = int(port)
        self.port = int(port)
        self.line_timing = bool(line_timing)
        self.reply_latency_s = reply_latency_s
        self.tick_s = tick_s
        self.link = LinkFaults(corrupt=garble_one)     # corrupt_reply: one character
        self.drives: dict[str, XplusMtDriveSim] = {
            d.name: XplusMtDriveSim(d, word_order=word_order, storage_dir=storage_dir,
                                  strict=strict, clock=clock) for d in drives}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._stop_event: asyncio.Event | None = None
        self._error: BaseException | None = None

    # SimBackend ---------------------------------------------------------------------------
    @property
    def drive_names(self) -> list[str]:
        return list(self.drives)

    @property
    def address(self) -> str:
        return f'{self.host}:{self.port}'

    def true_position_steps(self, drive: str) -> float:
        return self._drive(drive).true_position_steps

    def start(self) -> str:
        if self._thread is not None:
            return self.address
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name='xplus_mt_sim', daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            self.stop()
            raise OSError('xplus_mt_sim: server did not start within 10 s')
        if self._error is not None:
            error = self._error
            self.stop()
            raise OSError(f'xplus_mt_sim: cannot listen on {self.host}:{self.requested_port}: '
                          f'{error}')
        return self.address

    def stop(self) -> None:
        logger.info('stopping')
        loop, thread = self._loop, self._thread
        if loop is not None and self._stop_event is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stop_event.set)
            except RuntimeError:
                pass
        if thread is not None:
            thread.join(10.0)
            if thread.is_alive():
                logger.warning('server thread still running after 10 s; exiting without it')
        self._thread = None
        self._loop = None

    def inject_fault(self, drive: str, kind: str, code: int = 0,
                     value: float = 0.0) -> tuple[bool, str]:
        if kind in LINK_KINDS:
            if kind == 'link_ok':
                self.link.set(OK)
            elif kind == 'late_reply':
                if not value > 0:
                    return False, 'late_reply needs value = delay in s (> 0)'
                self.link.set(LATE_REPLY, value)
            else:
                self.link.set(kind)
            return True, f'link: {self.link.mode}' + (f' ({value} s)' if kind == 'late_reply'
                                                      else '')
        if kind not in DRIVE_KINDS:
            return False, (f'unknown kind {kind!r}; kinds: {", ".join(LINK_KINDS + DRIVE_KINDS)}')
        if drive not in self.drives:
            return False, f'unknown drive {drive!r}; drives: {", ".join(self.drives)}'
        return self.drives[drive].inject(kind, int(code), float(value))

    def set_input(self, drive: str, name: str, value: bool = True,
                  release: bool = False) -> tuple[bool, str]:
        if drive not in self.drives:
            return False, f'unknown drive {drive!r}; drives: {", ".join(self.drives)}'
        return self.drives[drive].set_input(name, value, release)

    def _drive(self, name: str) -> XplusMtDriveSim:
        try:
            return self.drives[name]
        except KeyError:
            raise KeyError(f'unknown drive {name!r}; drives: {", ".join(self.drives)}') from None

    # Server thread --------------------------------------------------------------------------
    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        except BaseException as exc:   # reported to start(); the thread must end cleanly
            self._error = exc
            logger.exception('xplus_mt_sim server failed')
        finally:
            self._ready.set()
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()

    async def _main(self) -> None:
        self._stop_event = asyncio.Event()
        devices = [SimDevice(id=dev.unit_id, simdata=[self._block()],
                             action=functools.partial(self._action, dev))
                   for dev in self.drives.values()]
        devices.append(SimDevice(id=0, simdata=[self._block()], action=self._unknown_unit))
        server = ModbusTcpServer(devices, address=(self.host, 0))
        server.decoder = _XplusMtDecoder()      # before serving: each connection copies it
        proxy: FaultyTcpProxy | None = None
        ticker: asyncio.Task | None = None
        try:
            await server.serve_forever(background=True)
            internal_port = server.transport.sockets[0].getsockname()[1]
            proxy = FaultyTcpProxy(internal_port, self.link, host=self.host,
                                   port=self.requested_port)
            try:
                await proxy.start()
            except OSError as exc:
                self._error = exc
                return
            self.port = proxy.port
            ticker = asyncio.ensure_future(self._tick())
            logger.info('X-PLUS MT simulator on %s:%d, units %s', self.host, self.port,
                        ', '.join(str(d.unit_id) for d in self.drives.values()))
            self._ready.set()
            await self._stop_event.wait()
        finally:
            if ticker is not None:
                ticker.cancel()
                try:
                    await ticker
                except asyncio.CancelledError:
                    pass
            # bounded: a stuck connection must not keep the process alive after SIGINT (seen
            # once on a starved machine: the demo gave up on the simulator after 15 s)
            if proxy is not None:
                await _bounded(proxy.stop(), 'the TCP proxy')
            await _bounded(server.shutdown(), 'the Modbus server')
            logger.info('stopped')

    async def _tick(self) -> None:
        """Time-driven behaviour without traffic (homing, watchdog, HV-stable Switch On)."""
        loop = asyncio.get_running_loop()
        last = loop.time()
        while True:
            await asyncio.sleep(self.tick_s)
            now = loop.time()
            # a tick much later than asked: this process was not running (a real drive's
            # watchdog would have seen the requests that are now queued in the socket)
            stall = now - last - self.tick_s
            last = now
            for dev in self.drives.values():
                try:
                    if stall > self.tick_s:
                        dev.excuse(stall)
                    dev.update()
                except Exception:
                    logger.exception('%s: update failed', dev.name)

    @staticmethod
    def _block() -> SimData:
        return SimData(address=REGISTER_BLOCK[0], count=REGISTER_BLOCK[1], values=0,
                       datatype=DataType.REGISTERS)

    async def _action(self, dev: XplusMtDriveSim, function_code: int, start_address: int,
                      address: int, count: int, registers: list[int],
                      set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        """pymodbus SimDevice hook: the device model answers every request (FC 03/04/06/16 only:
        _XplusMtDecoder answers the others)."""
        if self.line_timing and self.reply_latency_s > 0:
            await asyncio.sleep(self.reply_latency_s)
        if set_values is not None:
            values = [int(v) for v in set_values]
            result = dev.write(address, values)
            lose = dev.lose_write_reply
            if lose is not None and lose[0] == address and values[0] & lose[1] == lose[1]:
                dev.lose_write_reply = None
                await asyncio.sleep(LOST_REPLY_HOLD_S)     # written, but no timely answer
            return result
        if function_code == 6:
            return None     # pymodbus reads back after FC06: echo what was written
        words = dev.read(address, count)
        if isinstance(words, ExcCodes):
            return words
        offset = address - start_address
        registers[offset:offset + count] = words
        return None

    @staticmethod
    async def _unknown_unit(function_code, start_address, address, count, registers,
                            set_values) -> ExcCodes:
        return ExcCodes.GATEWAY_NO_RESPONSE


# ROS executable -------------------------------------------------------------------------------

def build(node) -> XplusMtSim:
    """Declare the xplus_mt_sim parameters on `node` and build the simulator (see sim_node)."""
    from ..core.sim_node import declare, declare_drives
    host = declare(node, 'host', '127.0.0.1', 'listen address (127.0.0.1 only)')
    port = declare(node, 'port', 1502, 'Modbus TCP port (the drive uses 502, which needs root)')
    word_order = declare(node, 'word_order', 'little',
                         'initial register 1162: little (1) or big (0)')
    line_timing = declare(node, 'line_timing', False, 'add a 2 ms reply latency')
    storage_dir = declare(node, 'storage_dir', '',
                          'directory of the non-volatile copies (save 0x6173); empty = RAM only')
    strict = declare(node, 'strict', True, 'exception 0x02 for reads over unmapped addresses '
                     '(false: they read 0), spec §1.3')
    if not 0 <= port <= 65535:
        raise ValueError(f'parameter port: {port} not in 0..65535')
    per_drive = {
        'unit_id': (1, 'Modbus unit id (1..255)'),
        'home_switch_steps': (50_000.0, 'home switch (I0) low edge, raw steps; NaN = none'),
        'home_switch_width_steps': (6_400.0, 'home switch width in steps (inf = half axis)'),
        'limit_neg_steps': (-1_000_000.0, 'negative limit switch position; NaN = none'),
        'limit_pos_steps': (1_000_000.0, 'positive limit switch position; NaN = none'),
        'hv_present': (True, 'power stage supply present at start'),
        'model': ('S4', 'S4 or B4 (output configurations of 1089)'),
        'input_config': (-1, 'initial Input Config 1088 (14: I0 = proximity input); '
                             '-1 = drive default 15 or the stored value'),
    }
    drive_params = declare_drives(node, ['axis1'], per_drive)
    configs = []
    for name, p in drive_params.items():
        try:
            configs.append(XplusMtDriveConfig(
                name=name, unit_id=int(p['unit_id']), home_switch_steps=p['home_switch_steps'],
                home_switch_width_steps=p['home_switch_width_steps'],
                limit_neg_steps=p['limit_neg_steps'], limit_pos_steps=p['limit_pos_steps'],
                hv_present=bool(p['hv_present']), model=str(p['model']),
                input_config=None if p['input_config'] < 0 else int(p['input_config'])))
        except ValueError as exc:
            raise ValueError(f'parameter drives.{name}: {exc}') from None
    return XplusMtSim(host=host, port=port, drives=configs, word_order=word_order,
                      line_timing=line_timing, storage_dir=storage_dir or None, strict=strict)


def main(args: Sequence[str] | None = None) -> None:
    from ..core.sim_node import run_sim
    sys.exit(run_sim('xplus_mt_sim', build, args=args))


if __name__ == '__main__':
    main()
