"""One remote CANopen node on a CanBus: `RemoteDrive`, a canopen.BaseNode402 plus what the
library leaves to the application:
  - a boot-up latch armed before an NMT reset (NmtMaster.wait_for_bootup() only looks at the
    last state received, so a heartbeat right behind the boot-up hides it: transports.md A5.3),
  - a heartbeat consumer with a deadline (the library has none: A5.4),
  - EMCY and TPDO reception counters, the last EMCY,
  - SDO access that raises the project's errors: an abort is an SdoAbortError (a DriveError
    naming the code and its CiA 301 text), no answer is a LinkError (the node then reconnects),
  - step-wise waits and PDO configuration (`drive.Operation`: one SDO per step).
NMT commands are sent as raw frames: canopen's NmtMaster.send_command() looks the last received
heartbeat state up in a table and raises KeyError for a state byte it does not know.
Also here: the checks of the frames a node sends (heartbeat, EMCY, SDO answer, TxPDO lengths)
that the bus runs before canopen sees them, and pack/unpack of SDO data.

Not here: the bus, its network, its receive thread and SYNC producer (canopen_link.CanBus, which
re-exports what this module holds). This module does not import canopen_link (which imports it):
what a RemoteDrive uses of its bus is the Protocol `NodeBus`. No rclpy here.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import struct
import threading
import time
from typing import Any, Callable, Protocol

import can
import canopen
from canopen.emcy import EmcyError
from canopen.objectdictionary import ObjectDictionaryError, ODVariable, datatypes
from canopen.sdo.base import SdoVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..contract.drive import DriveError, LinkError, Operation
from .cia301 import (
    EMCY_NO_ERROR,
    PDO_COB_BASES_RX,
    PDO_COB_BASES_TX,
    PDO_INVALID,
    RPDO_COMMUNICATION,
    RPDO_MAPPING,
    TPDO_COMMUNICATION,
    TPDO_MAPPING,
    abort_text,
    mapping_entry,
)

logger = logging.getLogger(__name__)

# canopen logs every SDO timeout ("Transfer aborted by client"); RemoteDrive reports them itself.
logging.getLogger('canopen.sdo.client').setLevel(logging.ERROR)

POLL_S = 0.002                 # step of a wait on something the receive thread records
# CiA 301 NMT: command specifiers and the states a heartbeat may report (bit 7 is reserved).
NMT_COMMANDS = {'OPERATIONAL': 0x01, 'STOPPED': 0x02, 'PRE-OPERATIONAL': 0x80,
                'RESET': 0x81, 'RESET COMMUNICATION': 0x82}
NMT_STATES = {0x00: 'BOOT-UP', 0x04: 'STOPPED', 0x05: 'OPERATIONAL', 0x7F: 'PRE-OPERATIONAL'}
# [COMMUNICATION CYCLE PERIOD] 0x1006 (us; 0 = not used): a drive that gets no SYNC for that long
# raises its "missing SYNC" alarm (Ralarm32 bit 18); what a drive was written is what the link
# watches its SYNC gaps against (RemoteDrive.write, CanBus.sync_watch)
COMMUNICATION_CYCLE_PERIOD = 0x1006
PDO_STRUCT_CHARS = {datatypes.INTEGER8: 'b', datatypes.INTEGER16: 'h', datatypes.INTEGER32: 'i',
                    datatypes.UNSIGNED8: 'B', datatypes.UNSIGNED16: 'H',
                    datatypes.UNSIGNED32: 'I'}


class SdoAbortError(DriveError):
    """The node answered an SDO with an abort; `code` is the CiA 301 abort code."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


class NodeBus(Protocol):
    """What a RemoteDrive uses of its bus (canopen_link.CanBus): its network, its frame checks
    and counters, its SYNC watch."""

    description: str
    timeout_s: float
    generation: int                  # +1 at every open(): drives re-attach their nodes
    frame_checks: dict[int, Callable[[bytes], str]]   # COB-ID -> problem or ''
    extra: dict[str, int]
    transactions: int
    errors: int
    changes: int

    @property
    def is_open(self) -> bool: ...

    def check(self) -> canopen.Network: ...

    def send(self, can_id: int, data: bytes) -> None: ...

    def sync_watch(self, name: str, timeout_s: float) -> None: ...


def check_length(length: int, what: str) -> Callable[[bytes], str]:
    def check(data: bytes) -> str:
        return '' if len(data) == length else f'{what} has {length} bytes, not {len(data)}'
    return check


_SDO_ANSWER_LENGTH = check_length(8, 'an SDO answer')


def check_heartbeat(data: bytes) -> str:
    if len(data) != 1:
        return f'a heartbeat has 1 byte, not {len(data)}'
    if data[0] & 0x7F not in NMT_STATES:
        return (f'heartbeat NMT state 0x{data[0]:02X} is not a CiA 301 state '
                f'({", ".join(f"0x{k:02X}" for k in NMT_STATES)})')
    return ''


@dataclasses.dataclass
class EmcyRecord:
    code: int
    register: int
    data: bytes
    time_s: float            # time.monotonic() at reception
    text: str                # the device maker's text for the code (RemoteDrive.emcy_text)


def emcy_code_text(code: int, vendor_data: bytes = b'') -> str:
    """An EMCY code without a maker's table (CiA 301 leaves the texts to the device)."""
    return f'error code 0x{code:04X}'


class RemoteDrive:
    """One CANopen slave on a CanBus: node object, heartbeat, boot-up latch, EMCY, SDO helpers."""

    def __init__(self, bus: NodeBus, node_id: int, eds: str, name: str = '',
                 emcy_text: Callable[[int, bytes], str] = emcy_code_text):
        self.bus = bus
        self.node_id = node_id
        self.eds = eds
        self.emcy_text = emcy_text     # (code, manufacturer bytes 3..7) -> the maker's text
        self.name = name or f'node {node_id}'
        self.node: canopen.BaseNode402 | None = None
        self._generation = -1
        # What the receive thread records, several fields at a time: a waiter reads them under
        # this lock (the waits are step-wise, nobody blocks on it).
        self._lock = threading.Lock()
        self.bootups = 0                   # boot-up frames seen (state 0)
        self.heartbeat_at: float | None = None
        self.heartbeat_state: int | None = None
        self.tpdo_at: float | None = None
        self.emcy: EmcyRecord | None = None   # last EMCY with a code other than 0x0000
        self.emcy_count = 0
        self.emcy_listeners: list[Callable[[EmcyRecord], None]] = []
        # +1 (receive thread) for each frame that may change what the node shows: a TxPDO whose
        # bytes differ from the last one on its COB-ID, a heartbeat with another state or a
        # boot-up, an EMCY; counted after what the frame changed is stored. Unchanged since a
        # reader looked (before it read anything else), nothing received since has changed
        # anything but the heartbeat's time (the drive's state cache, read_state()).
        self.changes = 0
        self._tpdo_last: dict[int, bytes] = {}
        self._tpdo_handler: Callable[[int, bytearray], None] | None = None
        self._tpdo_cobs: list[int] = []    # the COB-IDs _tpdo_frame is subscribed to
        checks = bus.frame_checks
        checks[0x700 + node_id] = check_heartbeat
        checks[0x080 + node_id] = check_length(8, 'an EMCY')            # COB-ID 0x1014
        checks[0x580 + node_id] = self._check_sdo_answer
        # SDO answers received since the request in flight (receive thread): its errors
        # name them
        self.sdo_answers: collections.deque[bytes] = collections.deque(maxlen=4)

    def _check_sdo_answer(self, data: bytes) -> str:
        self.sdo_answers.append(bytes(data))
        return _SDO_ANSWER_LENGTH(data)

    def _received(self) -> str:
        answers = list(self.sdo_answers)
        if not answers:
            return 'nothing received'
        return 'received ' + ', '.join(f'[{len(a)}] {a.hex(" ")}' for a in answers)

    # Attachment --------------------------------------------------------------------------------
    def attach(self) -> canopen.BaseNode402:
        """A fresh BaseNode402 on the bus' current network (at every connect)."""
        network = self.bus.check()
        old = self.node
        if old is not None and self._generation == self.bus.generation:
            # Network.add_node() drops the old node's SDO/NMT/EMCY callbacks, not its PDOs'
            # nor the TxPDO frames' (watch_tpdos).
            for pdo in list(old.tpdo.values()) + list(old.rpdo.values()):
                if pdo.enabled and pdo.cob_id in network.subscribers:
                    _unsubscribe(network, pdo.cob_id, pdo.on_message)
            for cob_id in self._tpdo_cobs:
                _unsubscribe(network, cob_id, self._tpdo_frame)
        self._tpdo_cobs, self._tpdo_handler = [], None
        node = canopen.BaseNode402(self.node_id, canopen.import_od(self.eds, self.node_id))
        node.sdo.RESPONSE_TIMEOUT = self.bus.timeout_s
        node.sdo.MAX_RETRIES = 1
        # the heartbeat frame straight to _heartbeat_frame: canopen's NmtMaster.on_heartbeat
        # keeps a state this driver never reads, under a condition nobody waits on. Set on the
        # node before add_node(), which subscribes it (and unsubscribes it with the node).
        node.nmt.on_heartbeat = self._heartbeat_frame
        network.add_node(node)
        node.emcy.add_callback(self._on_emcy)
        self.node = node
        self._generation = self.bus.generation
        with self._lock:
            self.heartbeat_at = None
            self.heartbeat_state = None
            self._tpdo_last = {}
            self.changes += 1
            self.bus.changes += 1
        return node

    @property
    def attached(self) -> bool:
        return self.node is not None and self._generation == self.bus.generation \
            and self.bus.is_open

    # Callbacks (receive thread) -----------------------------------------------------------------
    def _heartbeat_frame(self, _can_id: int, data: bytearray, _timestamp: float) -> None:
        """A heartbeat or boot-up (CiA 301 error control: one byte, the NMT state, bit 7 the
        node guarding toggle); check_heartbeat let only a well-formed one through."""
        state = data[0] & 0x7F
        with self._lock:
            self.heartbeat_at = time.monotonic()
            changed = state != self.heartbeat_state or state == 0
            self.heartbeat_state = state
            self.bus.extra['heartbeat_rx'] += 1
            if state == 0:
                self.bootups += 1
                self.bus.extra['bootups'] += 1
            if changed:                 # after what it counts: see `changes`
                self.changes += 1
                self.bus.changes += 1

    def _on_emcy(self, error: EmcyError) -> None:
        data = bytes(error.data)
        record = EmcyRecord(error.code, error.register, data, time.monotonic(),
                            self.emcy_text(error.code, data[:5]))
        self.bus.extra['emcy_rx'] += 1
        with self._lock:
            self.emcy_count += 1
            if error.code != EMCY_NO_ERROR:
                self.emcy = record
            self.changes += 1
            self.bus.changes += 1
        logger.info('%s: EMCY 0x%04X %s (error register 0x%02X, data %s)', self.name,
                    record.code, record.text, record.register, record.data.hex())
        for listener in list(self.emcy_listeners):
            listener(record)

    def _tpdo_frame(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        """A TxPDO of this node (its length checked by the network, configure_pdo): counted,
        timed and handed to the handler of watch_tpdos. canopen's PdoMap is not in the way: it
        decodes nothing the driver reads and locks a condition per frame that nobody waits on."""
        self.tpdo_at = time.monotonic()
        self.bus.extra['tpdo_rx'] += 1
        handler = self._tpdo_handler
        if handler is not None:
            handler(can_id, data)
        if data != self._tpdo_last.get(can_id):
            self._tpdo_last[can_id] = bytes(data)
            self.changes += 1
            self.bus.changes += 1

    # Waiting ------------------------------------------------------------------------------------
    def wait(self, condition: Callable[[], bool], timeout_s: float) -> Operation[bool]:
        """Step-wise wait for a condition on what the receive thread records (evaluated under
        this object's lock); True when met, False at the timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                if condition():
                    return True
            if time.monotonic() >= deadline:
                return False
            yield POLL_S

    def heartbeat_age_s(self) -> float | None:
        at = self.heartbeat_at
        return None if at is None else time.monotonic() - at

    # NMT -----------------------------------------------------------------------------------------
    def nmt(self, command: str) -> None:
        """Send an NMT command ('OPERATIONAL', 'PRE-OPERATIONAL', 'RESET COMMUNICATION' ...)."""
        self._node()
        self.bus.send(0x000, bytes([NMT_COMMANDS[command], self.node_id]))

    def reset_and_wait_bootup(self, command: str, timeout_s: float) -> Operation[bool]:
        """NMT reset (node or communication) with the boot-up latch armed before the frame."""
        with self._lock:
            seen = self.bootups
        self.nmt(command)
        return (yield from self.wait(lambda: self.bootups > seen, timeout_s))

    # SDO -----------------------------------------------------------------------------------------
    def _node(self) -> canopen.BaseNode402:
        if self.node is None or not self.attached:
            raise LinkError(f'{self.name}: not attached to {self.bus.description}')
        return self.node

    def _sdo(self, what: str, fn: Callable[[], Any], expected_aborts: tuple[int, ...] = ()
             ) -> Any:
        self.bus.transactions += 1
        self.sdo_answers.clear()
        try:
            return fn()
        except SdoAbortedError as exc:
            if exc.code not in expected_aborts:   # an answer the caller asks for is no error
                self.bus.errors += 1
            raise SdoAbortError(f'{what}: {abort_text(exc.code)}', exc.code) from None
        except SdoCommunicationError as exc:
            self.bus.errors += 1
            raise LinkError(f'{self.name} (node-ID {self.node_id}) gave no valid SDO answer to '
                            f'{what} within {self.bus.timeout_s:g} s: {exc} '
                            f'({self._received()})') from None
        except (can.CanError, OSError, RuntimeError) as exc:
            self.bus.errors += 1
            raise LinkError(f'{self.name}: {what}: {type(exc).__name__}: {exc}') from None

    def read(self, index: int, sub: int = 0, expected_aborts: tuple[int, ...] = ()) -> Any:
        """Read one object through its EDS type (raw value: int or str). An abort raises
        SdoAbortError; those in `expected_aborts` do not count as link errors."""
        node = self._node()
        what = f'read 0x{index:04X}:{sub:02X}'
        entry = self._entry(node, index, sub)
        data = self._sdo(what, lambda: entry.data, expected_aborts)
        try:
            return entry.od.decode_raw(data)
        except ObjectDictionaryError:      # an upload shorter than the object's type
            self.bus.errors += 1
            raise LinkError(f'{self.name} (node-ID {self.node_id}): {what} answered '
                            f'{len(data)} byte(s) {data.hex(" ")}, its EDS type has '
                            f'{len(entry.od) // 8} ({self._received()})') from None

    def write(self, index: int, sub: int, value: Any) -> None:
        node = self._node()
        what = f'write 0x{index:04X}:{sub:02X} = {value!r}'

        def do():
            self._entry(node, index, sub).raw = value
        self._sdo(what, do)
        if index == COMMUNICATION_CYCLE_PERIOD and sub == 0:
            self.bus.sync_watch(self.name, int(value) / 1e6)

    def pdo_struct(self, entries: tuple[tuple[int, int, int], ...]) -> struct.Struct:
        """The layout of a PDO that maps whole-byte integers, from their EDS data types: one
        unpack per frame, where canopen decodes it object by object (12.7 us against 1.1 us
        for a TxPDO of two objects). ValueError for an entry it cannot hold."""
        od = self._node().object_dictionary
        chars = []
        for index, sub, bits in entries:
            obj = od[index]
            if not isinstance(obj, ODVariable):
                obj = obj[sub]
            char = PDO_STRUCT_CHARS.get(obj.data_type)
            if char is None or struct.calcsize(char) * 8 != bits:
                raise ValueError(f'0x{index:04X}:{sub:02X} ({bits} bits, data type '
                                 f'0x{obj.data_type:04X}) is not a whole-byte integer')
            chars.append(char)
        return struct.Struct('<' + ''.join(chars))

    def limits(self, index: int, sub: int) -> tuple[int | None, int | None]:
        """LowLimit/HighLimit of an object in the EDS (None where it gives none)."""
        obj = self._node().object_dictionary[index]
        if not isinstance(obj, ODVariable):
            obj = obj[sub]
        return obj.min, obj.max

    @staticmethod
    def _entry(node: canopen.BaseNode402, index: int, sub: int):
        obj = node.sdo[index]
        if isinstance(obj, SdoVariable):
            return obj
        return obj[sub]

    def upload(self, index: int, sub: int) -> bytes:
        """Raw SDO upload (no EDS needed): the bytes the node sends."""
        node = self._node()
        return self._sdo(f'read 0x{index:04X}:{sub:02X}', lambda: node.sdo.upload(index, sub))

    def download(self, index: int, sub: int, data: bytes) -> None:
        node = self._node()
        self._sdo(f'write 0x{index:04X}:{sub:02X} = {data.hex(" ")}',
                  lambda: node.sdo.download(index, sub, data))
        if index == COMMUNICATION_CYCLE_PERIOD and sub == 0 and len(data) == 4:
            self.bus.sync_watch(self.name, int.from_bytes(data, 'little') / 1e6)

    # PDO configuration [COME MAPPARE UN PDO] --------------------------------------------------
    def configure_pdo(self, direction: str, number: int,
                      entries: tuple[tuple[int, int, int], ...], transmission_type: int = 0xFE,
                      event_timer_ms: int = 0, inhibit_time_100us: int = 0) -> Operation[None]:
        """Map one PDO (1..4) and enable it; an empty `entries` disables it. One SDO per step.

        The robust sequence of the digest's section 9 (canopen's PdoMap.save() order): COB-ID
        invalid, transmission type (TxPDO: inhibit time, event timer), mapping sub 0 = 0,
        entries, sub 0 = n (the manual's re-enable), COB-ID valid; then the local PdoMap decodes
        what arrives on the COB-ID.
        """
        node = self._node()
        tx = direction == 'tx'
        pdo = (node.tpdo if tx else node.rpdo)[number]
        pdo.clear()
        for index, sub, bits in entries:
            pdo.add_variable(index, sub, bits)
        cob_id = (PDO_COB_BASES_TX if tx else PDO_COB_BASES_RX)[number - 1] + self.node_id
        pdo.cob_id, pdo.trans_type, pdo.enabled = cob_id, transmission_type, bool(entries)
        comm = (TPDO_COMMUNICATION if tx else RPDO_COMMUNICATION) + number - 1
        mapping = (TPDO_MAPPING if tx else RPDO_MAPPING) + number - 1
        writes = [(comm, 1, cob_id | PDO_INVALID), (comm, 2, transmission_type)]
        if tx:
            pdo.event_timer, pdo.inhibit_time = event_timer_ms, inhibit_time_100us
            writes += [(comm, 3, inhibit_time_100us), (comm, 5, event_timer_ms)]
        writes.append((mapping, 0, 0))
        writes += [(mapping, k, mapping_entry(*entry)) for k, entry in enumerate(entries, 1)]
        writes.append((mapping, 0, len(entries)))
        if entries:
            writes.append((comm, 1, cob_id))
        for k, (index, sub, value) in enumerate(writes):
            if k:
                yield 0.0
            self.write(index, sub, value)
        if entries:
            pdo.subscribe()
            if tx:
                self.bus.frame_checks[cob_id] = check_length(
                    pdo.length // 8, f'TxPDO{number} (mapped)')

    def watch_tpdos(self, handler: Callable[[int, bytearray], None]) -> None:
        """The enabled TxPDOs' frames to handler(cob_id, data) (receive thread), counted and
        timed, instead of to canopen's PdoMap (after BaseNode402.setup_pdos, which subscribes
        the maps). The frame's bytes are the handler's to decode, as mapped."""
        network = self.bus.check()
        for cob_id in self._tpdo_cobs:
            _unsubscribe(network, cob_id, self._tpdo_frame)
        self._tpdo_handler = handler
        self._tpdo_cobs = []
        for pdo in self._node().tpdo.values():
            if pdo.enabled:
                _unsubscribe(network, pdo.cob_id, pdo.on_message)
                network.subscribe(pdo.cob_id, self._tpdo_frame)
                self._tpdo_cobs.append(pdo.cob_id)

    def wait_heartbeat_state(self, state: int, since: float, timeout_s: float) -> Operation[bool]:
        """Wait for a heartbeat received after `since` (time.monotonic()) showing `state`."""
        return (yield from self.wait(
            lambda: self.heartbeat_state == state and self.heartbeat_at is not None
            and self.heartbeat_at > since, timeout_s))


def _unsubscribe(network: canopen.Network, cob_id: int, callback: Callable) -> None:
    try:
        network.unsubscribe(cob_id, callback)
    except (KeyError, ValueError):
        pass


def pack(data_type: str, value: int) -> bytes:
    """Little-endian bytes of an integer of the given project type name (u8 .. i64)."""
    fmt = {'u8': '<B', 'i8': '<b', 'u16': '<H', 'i16': '<h', 'u32': '<I', 'i32': '<i',
           'u64': '<Q', 'i64': '<q'}[data_type]
    return struct.pack(fmt, value)


def unpack(data_type: str, data: bytes) -> int:
    fmt = {'u8': '<B', 'i8': '<b', 'u16': '<H', 'i16': '<h', 'u32': '<I', 'i32': '<i',
           'u64': '<Q', 'i64': '<q'}[data_type]
    return struct.unpack(fmt, data)[0]
