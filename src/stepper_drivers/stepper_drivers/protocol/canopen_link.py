"""CANopen master side on python-can + canopen 2.4.1: the bus, and one remote node's plumbing.

`CanBus` is one python-can bus (socketcand to the loopback broker in tests, `socketcan` `can0`
on hardware) with one `canopen.Network`; every drive on it is a `RemoteDrive` (a
`canopen.BaseNode402` plus what the library leaves to the application):
  - a boot-up latch armed before an NMT reset (NmtMaster.wait_for_bootup() only looks at the
    last state received, so a heartbeat right behind the boot-up hides it: transports.md A5.3),
  - a heartbeat consumer with a deadline (the library has none: A5.4),
  - EMCY and TPDO reception counters, the last EMCY,
  - SDO access that raises the project's errors: an abort is a DriveError naming the code and
    its CiA 301 text, no answer is a LinkError (the node then reconnects).
No rclpy here.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import struct
import threading
import time
from typing import Any, Callable

import can
import canopen
from canopen.emcy import EmcyError
from canopen.sdo.base import SdoVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..drive import Bus, DriveError, LinkError
from ..vendors import vector_step_map as vm

logger = logging.getLogger(__name__)

# python-can's socketcand client logs a warning whenever a TCP read ends mid-frame (harmless).
logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
# canopen logs every SDO timeout ("Transfer aborted by client"); RemoteDrive reports them itself.
logging.getLogger('canopen.sdo.client').setLevel(logging.ERROR)

BITRATES = (10000, 20000, 50000, 125000, 250000, 500000, 800000, 1000000)   # Rcanbaud 0..7
PROBE_TIMEOUT_S = 1.0


class CanBus(Bus):
    """One CAN bus (python-can) carrying one canopen.Network; several drives share it."""

    def __init__(self, interface: str = 'socketcand', channel: str = 'can0',
                 bitrate: int = 125000, host: str = '127.0.0.1', port: int = 29536,
                 timeout_s: float = 0.5):
        self.interface = interface
        self.channel = channel
        self.bitrate = int(bitrate)
        self.host = host
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.network: canopen.Network | None = None
        self.generation = 0              # +1 at every open(): drives re-attach their nodes
        self._node_ids: dict[int, str] = {}
        self.extra: dict[str, int] = {'tpdo_rx': 0, 'emcy_rx': 0, 'heartbeat_rx': 0,
                                      'bootups': 0}
        if interface == 'socketcand':
            self.description = f'CAN socketcand {host}:{port} {channel}'
        else:
            self.description = f'CAN {interface} {channel} {bitrate // 1000} kbit/s'

    def claim(self, node_id: int, name: str) -> None:
        """Reserve a node-ID for a drive; two drives with one node-ID is a configuration error."""
        other = self._node_ids.get(node_id)
        if other is not None and other != name:
            raise ValueError(f'drives.{name}.node_id: {node_id} is already the node-ID of '
                             f'drive {other!r} on this bus (allowed: 1..127, one per drive)')
        self._node_ids[node_id] = name

    def _bus_kwargs(self) -> dict[str, Any]:
        if self.interface == 'socketcand':
            return dict(interface='socketcand', channel=self.channel, host=self.host,
                        port=self.port, tcp_tune=True)
        return dict(interface=self.interface, channel=self.channel, bitrate=self.bitrate)

    def open(self) -> None:
        if self.interface == 'socketcand':
            # python-can retries connect() in a busy loop for 10 s: find out first.
            try:
                socket.create_connection((self.host, self.port), PROBE_TIMEOUT_S).close()
            except OSError as exc:
                raise LinkError(f'{self.description}: cannot connect ({exc}); is the '
                                'socketcand server (broker) running?') from None
        network = canopen.Network()
        network.NOTIFIER_CYCLE = 0.1               # close() waits one receive timeout
        try:
            network.connect(**self._bus_kwargs())
        except (can.CanError, OSError, ValueError, TimeoutError) as exc:
            raise LinkError(f'{self.description}: {type(exc).__name__}: {exc}') from None
        self.network = network
        self.generation += 1
        logger.info('opened %s', self.description)

    def close(self) -> None:
        network, self.network = self.network, None
        if network is None:
            return
        try:
            network.disconnect()
        except Exception as exc:  # noqa: BLE001 - a dead bus may fail to close in any way
            logger.debug('closing %s: %s', self.description, exc)

    @property
    def is_open(self) -> bool:
        return self.network is not None

    def check(self) -> canopen.Network:
        """The network, or LinkError when closed or its receive thread died."""
        network = self.network
        if network is None:
            raise LinkError(f'{self.description} is closed')
        try:
            network.check()
        except Exception as exc:  # noqa: BLE001 - whatever killed the notifier thread
            raise LinkError(f'{self.description}: receive thread stopped: {exc}') from None
        return network

    def send(self, can_id: int, data: bytes) -> None:
        try:
            self.check().send_message(can_id, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self.errors += 1
            raise LinkError(f'{self.description}: send 0x{can_id:03X} failed: {exc}') from None

    def counters(self) -> dict[str, int]:
        return {'transactions': self.transactions, 'errors': self.errors, **self.extra}


@dataclasses.dataclass
class EmcyRecord:
    code: int
    register: int
    data: bytes
    time_s: float            # time.monotonic() at reception

    @property
    def text(self) -> str:
        return vm.emcy_text(self.code, self.data[:5])


class RemoteDrive:
    """One CANopen slave on a CanBus: node object, heartbeat, boot-up latch, EMCY, SDO helpers."""

    def __init__(self, bus: CanBus, node_id: int, eds: str, name: str = ''):
        self.bus = bus
        self.node_id = node_id
        self.eds = eds
        self.name = name or f'node {node_id}'
        self.node: canopen.BaseNode402 | None = None
        self._generation = -1
        self._cond = threading.Condition()
        self.bootups = 0                   # boot-up frames seen (state 0)
        self.heartbeat_at: float | None = None
        self.heartbeat_state: int | None = None
        self.tpdo_count = 0                # TxPDOs received from this node
        self.tpdo_at: float | None = None
        self.emcy: EmcyRecord | None = None   # last EMCY with a code other than 0x0000
        self.emcy_count = 0
        self.emcy_listeners: list[Callable[[EmcyRecord], None]] = []

    # Attachment --------------------------------------------------------------------------------
    def attach(self) -> canopen.BaseNode402:
        """A fresh BaseNode402 on the bus' current network (at every connect)."""
        network = self.bus.check()
        old = self.node
        if old is not None and self._generation == self.bus.generation:
            # Network.add_node() drops the old node's SDO/NMT/EMCY callbacks, not its PDOs'.
            for pdo in list(old.tpdo.values()) + list(old.rpdo.values()):
                if pdo.enabled and pdo.cob_id in network.subscribers:
                    try:
                        network.unsubscribe(pdo.cob_id, pdo.on_message)
                    except (KeyError, ValueError):
                        pass
        node = canopen.BaseNode402(self.node_id, canopen.import_od(self.eds, self.node_id))
        node.sdo.RESPONSE_TIMEOUT = self.bus.timeout_s
        node.sdo.MAX_RETRIES = 1
        network.add_node(node)
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        self.node = node
        self._generation = self.bus.generation
        with self._cond:
            self.heartbeat_at = None
            self.heartbeat_state = None
        return node

    @property
    def attached(self) -> bool:
        return self.node is not None and self._generation == self.bus.generation \
            and self.bus.is_open

    # Callbacks (receive thread) -----------------------------------------------------------------
    def _on_heartbeat(self, state: int) -> None:
        with self._cond:
            self.heartbeat_at = time.monotonic()
            self.heartbeat_state = state
            self.bus.extra['heartbeat_rx'] += 1
            if state == 0:
                self.bootups += 1
                self.bus.extra['bootups'] += 1
            self._cond.notify_all()

    def _on_emcy(self, error: EmcyError) -> None:
        record = EmcyRecord(error.code, error.register, bytes(error.data), time.monotonic())
        self.bus.extra['emcy_rx'] += 1
        with self._cond:
            self.emcy_count += 1
            if error.code != vm.EMCY_NO_ERROR:
                self.emcy = record
            self._cond.notify_all()
        logger.info('%s: EMCY 0x%04X %s (error register 0x%02X, data %s)', self.name,
                    record.code, record.text, record.register, record.data.hex())
        for listener in list(self.emcy_listeners):
            listener(record)

    def on_tpdo(self, _map) -> None:
        with self._cond:
            self.tpdo_count += 1
            self.tpdo_at = time.monotonic()
            self.bus.extra['tpdo_rx'] += 1
            self._cond.notify_all()

    # Waiting ------------------------------------------------------------------------------------
    def wait(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        """Wait for a condition on this object's counters (evaluated under its lock)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not condition():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def heartbeat_age_s(self) -> float | None:
        at = self.heartbeat_at
        return None if at is None else time.monotonic() - at

    # NMT -----------------------------------------------------------------------------------------
    def nmt(self, command: str) -> None:
        """Send an NMT command ('OPERATIONAL', 'PRE-OPERATIONAL', 'RESET COMMUNICATION' ...)."""
        node = self._node()
        try:
            node.nmt.state = command
        except (can.CanError, OSError, RuntimeError) as exc:
            self.bus.errors += 1
            raise LinkError(f'{self.name}: NMT {command}: {type(exc).__name__}: {exc}') from None

    def reset_and_wait_bootup(self, command: str, timeout_s: float) -> bool:
        """NMT reset (node or communication) with the boot-up latch armed before the frame."""
        with self._cond:
            seen = self.bootups
        self.nmt(command)
        return self.wait(lambda: self.bootups > seen, timeout_s)

    # SDO -----------------------------------------------------------------------------------------
    def _node(self) -> canopen.BaseNode402:
        if self.node is None or not self.attached:
            raise LinkError(f'{self.name}: not attached to {self.bus.description}')
        return self.node

    def _sdo(self, what: str, fn: Callable[[], Any]) -> Any:
        self.bus.transactions += 1
        try:
            return fn()
        except SdoAbortedError as exc:
            self.bus.errors += 1
            raise DriveError(f'{what}: {vm.abort_text(exc.code)}') from None
        except SdoCommunicationError as exc:
            self.bus.errors += 1
            raise LinkError(f'{self.name} (node-ID {self.node_id}) gave no SDO answer to {what} '
                            f'within {self.bus.timeout_s:g} s: {exc}') from None
        except (can.CanError, OSError, RuntimeError) as exc:
            self.bus.errors += 1
            raise LinkError(f'{self.name}: {what}: {type(exc).__name__}: {exc}') from None

    def read(self, index: int, sub: int = 0) -> Any:
        """Read one object through its EDS type (raw value: int or str)."""
        node = self._node()
        what = f'read 0x{index:04X}:{sub:02X}'
        return self._sdo(what, lambda: self._entry(node, index, sub).raw)

    def write(self, index: int, sub: int, value: Any) -> None:
        node = self._node()
        what = f'write 0x{index:04X}:{sub:02X} = {value!r}'

        def do():
            self._entry(node, index, sub).raw = value
        self._sdo(what, do)

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

    # PDO configuration [COME MAPPARE UN PDO] --------------------------------------------------
    def configure_pdo(self, direction: str, number: int,
                      entries: tuple[tuple[int, int, int], ...], transmission_type: int = 0xFE,
                      event_timer_ms: int | None = None,
                      inhibit_time_100us: int | None = None) -> None:
        """Map one PDO (1..4) and enable it; an empty `entries` disables it.

        canopen's PdoMap.save() follows the robust sequence of the digest's section 9: COB-ID
        invalid, transmission type (TxPDO: inhibit time, event timer), mapping sub 0 = 0, entries,
        sub 0 = n (the manual's re-enable), COB-ID valid.
        """
        node = self._node()
        maps = node.tpdo if direction == 'tx' else node.rpdo
        bases = vm.PDO_COB_BASES_TX if direction == 'tx' else vm.PDO_COB_BASES_RX
        pdo = maps[number]
        pdo.clear()
        for index, sub, bits in entries:
            pdo.add_variable(index, sub, bits)
        pdo.cob_id = bases[number - 1] + self.node_id
        pdo.trans_type = transmission_type
        pdo.enabled = bool(entries)
        pdo.rtr_allowed = True
        if direction == 'tx':
            pdo.event_timer = event_timer_ms
            pdo.inhibit_time = inhibit_time_100us
        what = f'map {"Tx" if direction == "tx" else "Rx"}PDO{number}'
        self._sdo(what, pdo.save)

    def watch_tpdos(self) -> None:
        """Count and time the TxPDOs (after BaseNode402.setup_pdos, so that waiters see the
        values it has stored)."""
        for pdo in self._node().tpdo.values():
            if pdo.enabled and self.on_tpdo not in pdo.callbacks:
                pdo.add_callback(self.on_tpdo)

    def wait_heartbeat_state(self, state: int, since: float, timeout_s: float) -> bool:
        """Wait for a heartbeat received after `since` (time.monotonic()) showing `state`."""
        return self.wait(lambda: self.heartbeat_state == state and self.heartbeat_at is not None
                         and self.heartbeat_at > since, timeout_s)


def pack(data_type: str, value: int) -> bytes:
    """Little-endian bytes of an integer of the given project type name (u8 .. i64)."""
    fmt = {'u8': '<B', 'i8': '<b', 'u16': '<H', 'i16': '<h', 'u32': '<I', 'i32': '<i',
           'u64': '<Q', 'i64': '<q'}[data_type]
    return struct.pack(fmt, value)


def unpack(data_type: str, data: bytes) -> int:
    fmt = {'u8': '<B', 'i8': '<b', 'u16': '<H', 'i16': '<h', 'u32': '<I', 'i32': '<i',
           'u64': '<Q', 'i64': '<q'}[data_type]
    return struct.unpack(fmt, data)[0]
