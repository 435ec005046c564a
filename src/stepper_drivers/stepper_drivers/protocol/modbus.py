"""The Modbus application layer that the TCP and the RTU links share: request PDUs, reply
parsing, exception replies, and the one bus interface both links offer.

No rclpy. MODBUS Application Protocol Specification V1.1b3 (the R.T.A. and Lika manuals defer to
it: X-PLUS MT §11, RD4 §7.2 and §8.2). A PDU is the function code and its data; the RTU frame puts
the slave address before it and the CRC after it, the TCP frame the MBAP header before it.

Every link offers `ModbusBus`: `read_holding_registers`, `read_input_registers`,
`write_register` (FC06), `write_registers` (FC16), with one unit/slave address first, as pymodbus
names them. Errors, the same on both links:
- `ModbusExceptionError` (a `drive.DriveError`): the device answered with an exception; the link
  is fine. `.code` is the exception code, `.function_code` the request's.
- `drive.LinkError`: no answer, a broken or mismatched answer, or the link down; the caller
  reconnects.
- `drive.DriveError` (plain): a request this layer refuses to send (a count out of range).
"""

from __future__ import annotations

import abc
import dataclasses
import struct
from typing import Mapping, Sequence

from pymodbus.constants import ExcCodes

from .. import drive

FC_READ_HOLDING_REGISTERS = 0x03
FC_READ_INPUT_REGISTERS = 0x04
FC_WRITE_SINGLE_REGISTER = 0x06
FC_WRITE_MULTIPLE_REGISTERS = 0x10
FUNCTION_CODES = (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS, FC_WRITE_SINGLE_REGISTER,
                  FC_WRITE_MULTIPLE_REGISTERS)
READ_FUNCTION_CODES = (FC_READ_HOLDING_REGISTERS, FC_READ_INPUT_REGISTERS)
EXCEPTION_FLAG = 0x80                 # §7: exception function code = FC + 0x80

MAX_READ_COUNT = 125                  # §6.3/§6.4: 1 to 125 (0x7D)
MAX_WRITE_COUNT = 123                 # §6.12: 1 to 123 (0x7B)

# The codes are pymodbus's; the names are the specification's (§7), which is where a user looks
# them up: pymodbus's member names are shortened (ILLEGAL_ADDRESS for ILLEGAL DATA ADDRESS) and
# one is misspelt (GATEWAY_PATH_UNAVIABLE).
ILLEGAL_FUNCTION = int(ExcCodes.ILLEGAL_FUNCTION)
ILLEGAL_DATA_ADDRESS = int(ExcCodes.ILLEGAL_ADDRESS)
ILLEGAL_DATA_VALUE = int(ExcCodes.ILLEGAL_VALUE)
SERVER_DEVICE_FAILURE = int(ExcCodes.DEVICE_FAILURE)
EXCEPTION_NAMES: Mapping[int, str] = {
    ILLEGAL_FUNCTION: 'ILLEGAL FUNCTION',
    ILLEGAL_DATA_ADDRESS: 'ILLEGAL DATA ADDRESS',
    ILLEGAL_DATA_VALUE: 'ILLEGAL DATA VALUE',
    SERVER_DEVICE_FAILURE: 'SERVER DEVICE FAILURE',
    int(ExcCodes.ACKNOWLEDGE): 'ACKNOWLEDGE',
    int(ExcCodes.DEVICE_BUSY): 'SERVER DEVICE BUSY',
    int(ExcCodes.MEMORY_PARITY_ERROR): 'MEMORY PARITY ERROR',
    int(ExcCodes.GATEWAY_PATH_UNAVIABLE): 'GATEWAY PATH UNAVAILABLE',
    int(ExcCodes.GATEWAY_NO_RESPONSE): 'GATEWAY TARGET DEVICE FAILED TO RESPOND',
}


class ModbusExceptionError(drive.DriveError):
    """An exception reply: raised by the simulators' handlers, decoded by the masters."""

    def __init__(self, function_code: int, code: int, text: str = ''):
        self.function_code = function_code & 0x7F
        self.code = code
        name = EXCEPTION_NAMES.get(code, 'UNKNOWN EXCEPTION')
        super().__init__(f'exception 0x{code:02X} {name}' + (f': {text}' if text else ''))

    def within(self, context: str) -> 'ModbusExceptionError':
        """The same exception, its message prefixed with where it happened."""
        exc = ModbusExceptionError(self.function_code, self.code)
        exc.args = (f'{context}: {self}',)
        return exc


class ReplyMismatch(Exception):
    """A well-formed reply that does not answer the request (FC, length, echo)."""


@dataclasses.dataclass(slots=True)      # not frozen: a frozen __init__ costs ~1 us a field
class Request:
    """One request PDU with its unit (slave) address; `values` only for writes."""

    unit: int
    function_code: int
    address: int
    count: int = 1
    values: tuple[int, ...] = ()

    def pdu(self) -> bytes:
        fc = self.function_code
        head = bytes((fc,)) + self.address.to_bytes(2, 'big')
        if fc in READ_FUNCTION_CODES:
            return head + self.count.to_bytes(2, 'big')
        if fc == FC_WRITE_SINGLE_REGISTER:
            return head + (self.values[0] & 0xFFFF).to_bytes(2, 'big')
        if fc == FC_WRITE_MULTIPLE_REGISTERS:
            data = b''.join((v & 0xFFFF).to_bytes(2, 'big') for v in self.values)
            return head + len(self.values).to_bytes(2, 'big') + bytes((len(data),)) + data
        raise ValueError(f'function code 0x{fc:02X} is not implemented (03, 04, 06, 16)')

    @property
    def reply_pdu_length(self) -> int:
        """Bytes of the normal reply PDU (§6.3, §6.4, §6.6, §6.12)."""
        return 2 + 2 * self.count if self.function_code in READ_FUNCTION_CODES else 5

    def describe(self, hex_address: bool = False) -> str:
        """'FC03 read 21 at 1001'; addresses in hex where the manual numbers them so (RD4)."""
        fc = self.function_code
        at = f'0x{self.address:02X}' if hex_address else str(self.address)
        if fc in READ_FUNCTION_CODES:
            return f'FC{fc:02d} read {self.count} at {at}'
        if fc == FC_WRITE_SINGLE_REGISTER:
            return f'FC06 write 0x{self.values[0]:04X} at {at}'
        return f'FC16 write {self.count} at {at}'


def read_request(unit: int, function_code: int, address: int, count: int) -> Request:
    if function_code not in READ_FUNCTION_CODES:
        raise ValueError(f'not a read function code: {function_code}')
    if not 1 <= count <= MAX_READ_COUNT:
        raise ValueError(f'read of {count} registers at {address}: count {count} outside '
                         f'1..{MAX_READ_COUNT}')
    return Request(unit, function_code, address, count)


def write_single_request(unit: int, address: int, value: int) -> Request:
    return Request(unit, FC_WRITE_SINGLE_REGISTER, address, 1, (int(value) & 0xFFFF,))


def write_multiple_request(unit: int, address: int, values: Sequence[int]) -> Request:
    if not 1 <= len(values) <= MAX_WRITE_COUNT:
        raise ValueError(f'write of {len(values)} registers at {address}: count {len(values)} '
                         f'outside 1..{MAX_WRITE_COUNT}')
    return Request(unit, FC_WRITE_MULTIPLE_REGISTERS, address, len(values),
                   tuple(int(v) & 0xFFFF for v in values))


def parse_reply_pdu(pdu: bytes, request: Request) -> list[int]:
    """Registers of a read reply ([] for a write); ModbusExceptionError, ReplyMismatch."""
    if not pdu:
        raise ReplyMismatch('empty reply')
    fc = pdu[0]
    if fc == request.function_code | EXCEPTION_FLAG:
        if len(pdu) != 2:
            raise ReplyMismatch(f'exception reply of {len(pdu)} bytes')
        raise ModbusExceptionError(fc, pdu[1])
    if fc != request.function_code:
        raise ReplyMismatch(f'reply with function code 0x{fc:02X} to '
                            f'0x{request.function_code:02X}')
    if fc in READ_FUNCTION_CODES:
        if len(pdu) < 2 or pdu[1] != 2 * request.count or len(pdu) != 2 + pdu[1]:
            raise ReplyMismatch(f'{len(pdu) - 2} data bytes for {request.count} registers')
        return list(struct.unpack_from(f'>{request.count}H', pdu, 2))
    if fc == FC_WRITE_SINGLE_REGISTER:
        if pdu != request.pdu():
            raise ReplyMismatch(f'FC06 reply {pdu.hex(" ")} is not the echo of '
                                f'{request.pdu().hex(" ")}')
        return []
    if pdu[1:5] != request.pdu()[1:5]:
        raise ReplyMismatch(f'FC16 reply for address/quantity {pdu[1:5].hex(" ")}, asked '
                            f'{request.pdu()[1:5].hex(" ")}')
    return []


class ModbusBus(drive.Bus):
    """What the Modbus TCP and RTU links both offer; a link implements `transact()`."""

    def read_holding_registers(self, unit: int, address: int, count: int) -> list[int]:
        """FC03 Read Holding Registers."""
        return self.transact(self._checked(read_request, unit, FC_READ_HOLDING_REGISTERS,
                                           address, count))

    def read_input_registers(self, unit: int, address: int, count: int) -> list[int]:
        """FC04 Read Input Registers."""
        return self.transact(self._checked(read_request, unit, FC_READ_INPUT_REGISTERS,
                                           address, count))

    def write_register(self, unit: int, address: int, value: int) -> None:
        """FC06 Write Single Register."""
        self.transact(write_single_request(unit, address, value))

    def write_registers(self, unit: int, address: int, values: Sequence[int]) -> None:
        """FC16 Write Multiple Registers."""
        self.transact(self._checked(write_multiple_request, unit, address, values))

    @abc.abstractmethod
    def transact(self, request: Request) -> list[int]:
        """Send one request, return the registers read ([] for a write); the errors above."""

    def _checked(self, build, *args) -> Request:
        try:
            return build(*args)
        except ValueError as exc:
            raise drive.DriveError(f'{self.description}: {exc}') from None
