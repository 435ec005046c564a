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

The register maps of the Modbus devices (vendors/*_map.py) are made of `Register`; the
`read_register`/`write_register` services of their drivers parse the register a request names
with `parse_raw_register`, the device's specifics given as `RawRegisterRules`.
"""

from __future__ import annotations

import abc
import dataclasses
import struct
from typing import Callable, Mapping, Sequence

from pymodbus.constants import ExcCodes

from ..contract import drive

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


# ------------------------------------------------------------------------------ register maps
HOLDING = 'holding'        # holding registers: FC03 read, FC06/FC16 write
INPUT = 'input'            # input registers: FC04 read only

_DTYPE_WORDS = {'u16': 1, 'i16': 1, 'u32': 2, 'i32': 2}
_HEX_UNITS = ('bitfield', 'signature', 'code')     # values shown as 0x0000 in range texts


@dataclasses.dataclass(frozen=True)
class Register:
    """One entry of a Modbus device's register map: pure data, shared by driver and simulator.

    `access` is spelt 'ro', 'rw' or 'wo', in lower case as the RD4 manual (§8.1 attribute) and
    the CANopen object dictionaries (vendors/vector_step/regmap.py) write it; the X-PLUS MT tables
    print it in upper case. `storable` says that the device's save command keeps the register
    in its non-volatile memory: a property of the register, where `saved` would read as a state
    ("has been saved").
    """

    name: str              # UPPER_SNAKE of the manual's name, e.g. 'CONTROL_WORD'
    address: int           # protocol (PDU) address on the wire; the lower one of a 32-bit pair
    dtype: str             # 'u16' | 'i16' | 'u32' | 'i32' (U8 values take a whole u16 register)
    access: str            # 'ro' | 'rw' | 'wo'
    default: int = 0
    min: int = 0
    max: int = 0xFFFF
    unit: str = ''         # 'steps', 'Hz', 'ms', ...; 'bitfield', 'signature', 'code': hex values
    storable: bool = False     # stored by the save command (X-PLUS MT App.1 '**', RD4 CW bit 9)
    table: str = HOLDING       # HOLDING (FC03/06/16) or INPUT (FC04)
    title: str = ''            # the manual's heading where it has one, e.g. 'Control Word [0x2A]'
    # Where the manual lists discrete values only (signatures, codes), the values a write may
    # carry; empty = any value in min..max.
    allowed: tuple[int, ...] = ()
    wp_bit: int | None = None  # RD4: bit in Wrong parameters list [0x09-0x0A] (§8.1.2)

    @property
    def words(self) -> int:
        return _DTYPE_WORDS[self.dtype]

    @property
    def signed(self) -> bool:
        return self.dtype.startswith('i')

    @property
    def reg_no(self) -> int:
        """The 1-based register number (RD4 §7.4.1 "registers numbered 1-16 are addressed as
        0-15")."""
        return self.address + 1

    @property
    def writable(self) -> bool:
        return self.table == HOLDING and self.access in ('rw', 'wo')

    def accepts(self, value: int) -> bool:
        """True when `value` is a value this register may be written with."""
        if self.allowed:
            return value in self.allowed
        return self.min <= value <= self.max

    def range_text(self) -> str:
        if self.allowed:
            return 'one of ' + ', '.join(self._fmt(v) for v in self.allowed)
        return f'{self._fmt(self.min)}..{self._fmt(self.max)}'

    def _fmt(self, value: int) -> str:
        return f'0x{value:04X}' if self.unit in _HEX_UNITS else str(value)

    def __str__(self) -> str:
        return self.title or f'{self.name} ({self.address})'


@dataclasses.dataclass(frozen=True)
class RawRegisterRules:
    """What one device's `read_register`/`write_register` services accept as a register, and
    the words of their refusals: str.format templates with the fields named above each."""

    device: str                    # in 'data type u8 not supported by the <device> (allowed: ..)'
    registers: Sequence[Register]  # the register map, every table
    dtypes: tuple[str, ...]        # the data types a request may name
    # {address}: the address as the request gives it
    not_a_number: str
    # {table}, {number}, {dtype}, {end}: an address outside the map
    outside: str
    # {number}, {owner}: the address of the second word of a 32-bit register
    second_word: str
    # {reg}, {dtype}, {bits}: a register named with a data type of another width
    mismatch: str
    # {reg}: a write to a register that is not writable
    read_only: str
    # {number}: a write to an input register
    input_read_only: str = ''
    # The last address of each table: an address up to it where no register starts (a hole)
    # may be read and written as it is. Empty: the map's registers only.
    ends: Mapping[str, int] = dataclasses.field(default_factory=dict)
    # Table prefixes before the address, e.g. ('hr:', HOLDING); without one: HOLDING.
    prefixes: tuple[tuple[str, str], ...] = ()
    find: Callable[[str], Register | None] | None = None    # a register by name, or None
    # When the address and the data type are both wrong, the data type is refused first.
    type_first: bool = False


def parse_raw_register(rules: RawRegisterRules, address: str, data_type: str,
                       write: bool) -> Register:
    """The register a `read_register`/`write_register` request names; DriveError if refused.

    `address`: a number (1001, 0x3E9), after one of `rules.prefixes` if any, or a name that
    `rules.find` knows. The result is the map's register, or for a hole (see
    `RawRegisterRules.ends`) a nameless register of `data_type` at that address."""
    if rules.type_first:
        dtype = _raw_type(rules, data_type)
        table, number = _locate(rules, address)
    else:
        table, number = _locate(rules, address)
        dtype = _raw_type(rules, data_type)
    words = _DTYPE_WORDS[dtype]
    end = rules.ends.get(table)
    if end is not None and not 0 <= number <= end - words + 1:
        raise drive.DriveError(rules.outside.format(table=table, number=number, dtype=dtype,
                                                    end=end))
    registers = [r for r in rules.registers if r.table == table]
    reg = next((r for r in registers if r.address == number), None)
    if reg is None:
        owner = next((r for r in registers if r.words == 2 and r.address + 1 == number), None)
        if owner is not None:
            raise drive.DriveError(rules.second_word.format(number=number, owner=owner))
        if end is None:
            raise drive.DriveError(rules.outside.format(table=table, number=number, dtype=dtype,
                                                        end=end))
        reg = Register(name='', address=number, dtype=dtype,
                       access='ro' if table == INPUT else 'rw', table=table)
    elif reg.words != words:
        raise drive.DriveError(rules.mismatch.format(reg=reg, dtype=dtype, bits=16 * reg.words))
    if write:
        if table == INPUT:
            raise drive.DriveError(rules.input_read_only.format(number=number))
        if not reg.writable:
            raise drive.DriveError(rules.read_only.format(reg=reg))
    return reg


def _raw_type(rules: RawRegisterRules, data_type: str) -> str:
    dtype = drive.register_type(data_type).name
    if dtype not in rules.dtypes:
        raise drive.DriveError(f'data type {dtype} not supported by the {rules.device} '
                               f'(allowed: {", ".join(rules.dtypes)})')
    return dtype


def _locate(rules: RawRegisterRules, address: str) -> tuple[str, int]:
    """(table, address) from the request's address text."""
    text = str(address).strip()
    table = HOLDING
    for prefix, name in rules.prefixes:
        if text.lower().startswith(prefix):
            table, text = name, text[len(prefix):].strip()
            break
    reg = rules.find(text) if rules.find else None
    if reg is not None:
        return reg.table, reg.address
    try:
        return table, int(text, 0)
    except ValueError:
        raise drive.DriveError(rules.not_a_number.format(address=address)) from None
