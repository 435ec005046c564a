"""Modbus TCP link (holding registers only) around pymodbus 3.16.1's sync ModbusTcpClient.

No rclpy. Raises drive.LinkError when the link is down or a request gets no answer, and
drive.DriveError for a Modbus exception reply (the link is fine, the device said no). Reconnecting
is the caller's job: after a LinkError it calls close(), later open().
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Mapping, Sequence

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from .. import drive

logger = logging.getLogger(__name__)

# Modbus Application Protocol v1.1b3 §7 exception codes.
EXCEPTION_NAMES: Mapping[int, str] = {
    0x01: 'ILLEGAL FUNCTION',
    0x02: 'ILLEGAL DATA ADDRESS',
    0x03: 'ILLEGAL DATA VALUE',
    0x04: 'SERVER DEVICE FAILURE',
    0x05: 'ACKNOWLEDGE',
    0x06: 'SERVER DEVICE BUSY',
    0x08: 'MEMORY PARITY ERROR',
    0x0A: 'GATEWAY PATH UNAVAILABLE',
    0x0B: 'GATEWAY TARGET DEVICE FAILED TO RESPOND',
}

FC_READ_HOLDING_REGISTERS = 0x03
FC_WRITE_SINGLE_REGISTER = 0x06
FC_WRITE_MULTIPLE_REGISTERS = 0x10
MAX_READ_COUNT = 125     # Modbus limit for FC03
MAX_WRITE_COUNT = 123    # Modbus limit for FC16


class ModbusExceptionError(drive.DriveError):
    """The device answered with a Modbus exception (`code`, e.g. 0x02): the link is fine."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


class ModbusTcpBus(drive.Bus):
    """One TCP connection to a Modbus server; several unit ids may share it."""

    def __init__(self, host: str = '127.0.0.1', port: int = 502, timeout_s: float = 0.5):
        self.host = host
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.description = f'modbus tcp {host}:{self.port}'
        self.transactions = 0
        self.errors = 0
        self.exceptions = 0
        self.timeouts = 0
        self._lock = threading.Lock()
        self._client: ModbusTcpClient | None = None

    # Life cycle ---------------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            if self._client is not None and self._client.connected:
                return
            # retries=0: one attempt per request, so a dead link costs one timeout, not four.
            client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s,
                                     retries=0, reconnect_delay=0)
            if not client.connect():
                client.close()
                raise drive.LinkError(f'cannot connect to {self.host}:{self.port} '
                                      f'(modbus tcp, timeout {self.timeout_s:g} s)')
            self._client = client
            logger.info('connected to %s', self.description)

    def close(self) -> None:
        with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    @property
    def is_open(self) -> bool:
        client = self._client
        return client is not None and bool(client.connected)

    def counters(self) -> dict[str, int]:
        return {'transactions': self.transactions, 'errors': self.errors,
                'exceptions': self.exceptions, 'timeouts': self.timeouts}

    # Transactions -------------------------------------------------------------------------------
    def read_registers(self, unit_id: int, address: int, count: int) -> list[int]:
        """FC03 Read Holding Registers."""
        if not 1 <= count <= MAX_READ_COUNT:
            raise drive.DriveError(f'FC03 read at {address}: count {count} outside '
                                   f'1..{MAX_READ_COUNT}')
        what = f'FC03 read of {count} at {address}'
        reply = self._transact(what, unit_id, 'read_holding_registers', address,
                               count=count, device_id=unit_id)
        registers = list(reply.registers)
        if len(registers) < count:
            with self._lock:
                self.errors += 1
            raise drive.LinkError(f'{self.description} unit {unit_id}: {what}: '
                                  f'{len(registers)} registers in the reply')
        return registers[:count]

    def write_registers(self, unit_id: int, address: int, values: Sequence[int],
                        single: bool = False) -> None:
        """FC16 Write Multiple Registers; FC06 Write Single Register when `single` and 1 value."""
        values = [int(v) & 0xFFFF for v in values]
        if not 1 <= len(values) <= MAX_WRITE_COUNT:
            raise drive.DriveError(f'FC16 write at {address}: {len(values)} values outside '
                                   f'1..{MAX_WRITE_COUNT}')
        if single:
            if len(values) != 1:
                raise drive.DriveError(f'FC06 write at {address}: {len(values)} values, '
                                       f'FC06 carries one')
            self._transact(f'FC06 write at {address}', unit_id, 'write_register', address,
                           values[0], device_id=unit_id)
        else:
            self._transact(f'FC16 write at {address}', unit_id, 'write_registers', address,
                           values, device_id=unit_id)

    def _transact(self, what: str, unit_id: int, method: str, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            client = self._client
            if client is None:
                self.errors += 1
                raise drive.LinkError(f'{self.description}: not connected ({what})')
            self.transactions += 1
            try:
                reply = getattr(client, method)(*args, **kwargs)
            except ModbusIOException as exc:
                self.errors += 1
                self.timeouts += 1
                raise drive.LinkError(
                    f'{self.host}:{self.port} unit {unit_id}: {what}: no answer within '
                    f'{self.timeout_s:g} s') from exc
            except ConnectionException as exc:
                self.errors += 1
                raise drive.LinkError(
                    f'{self.host}:{self.port} unit {unit_id}: {what}: connection lost '
                    f'(timeout {self.timeout_s:g} s)') from exc
            except ModbusException as exc:
                self.errors += 1
                raise drive.LinkError(f'{self.host}:{self.port} unit {unit_id}: {what}: '
                                      f'{exc}') from exc
            except OSError as exc:   # pymodbus lets a reset connection through (issue 10)
                self.errors += 1
                raise drive.LinkError(f'{self.host}:{self.port} unit {unit_id}: {what}: '
                                      f'{exc.strerror or exc!r}') from exc
            if reply.isError():
                self.errors += 1
                self.exceptions += 1
                code = int(getattr(reply, 'exception_code', 0))
                name = EXCEPTION_NAMES.get(code, 'UNKNOWN EXCEPTION')
                raise ModbusExceptionError(f'{self.host}:{self.port} unit {unit_id}: {what}: '
                                           f'exception 0x{code:02X} {name}', code)
            return reply


def make_bus(params: Mapping[str, Any]) -> ModbusTcpBus:
    """Bus params 'host', 'port', 'timeout_s'; ValueError naming the parameter when unusable."""
    host = str(params.get('host', '127.0.0.1')).strip()
    if not host:
        raise ValueError("host: '' (allowed: an IP address or host name of the Modbus server)")
    try:
        port = int(params.get('port', 502))
    except (TypeError, ValueError):
        port = 0
    if not 1 <= port <= 65535:
        raise ValueError(f"port: {params.get('port')!r} (allowed: a TCP port 1..65535)")
    return ModbusTcpBus(host=host, port=port, timeout_s=float(params.get('timeout_s', 0.5)))
