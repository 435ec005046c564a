"""Vector Step simulator, PDO engine: a part of VectorStepNode.

The master's (re)mapping is honoured after every SDO write; TxPDOs on change, on their event timer
(re-armed at every event), spaced by the inhibit time, on SYNC (types 0..240) or on request
(252/253); RxPDOs into the object dictionary, applied at once (254/255) or at the next SYNC
(0..240); EMCY 0x8210/0x8220 on a length error (the manual's assignment).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
import dataclasses
import functools
import logging
import time
from typing import Any, Callable, Protocol

from canopen import LocalNode
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

from .nmt import NMT_INITIALISING, NMT_OPERATIONAL

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class Pdo:
    number: int
    direction: str                        # 'rx' or 'tx'
    cob_id: int = 0
    valid: bool = False
    rtr_allowed: bool = True
    trans_type: int = 0xFE
    inhibit_100us: int = 0
    event_timer_ms: int = 0
    entries: tuple[tuple[int, int, int], ...] = ()
    last_data: bytes | None = None
    last_sent: float = -1e9
    due: float | None = None              # a change waiting for the inhibit time
    sync_count: int = 0
    sampled: bytes | None = None           # type 252: data sampled at SYNC
    pending: bytes | None = None           # synchronous RxPDO waiting for SYNC
    handler: Callable | None = None

    @property
    def length(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8

    def timer_due(self) -> float | None:
        """When the event timer sends the unchanged data again (254/255); the inhibit time is
        the least interval between any two transmissions of the PDO (CiA 301), the timer's too."""
        if not self.event_timer_ms:
            return None
        return self.last_sent + max(self.event_timer_ms / 1000.0, self.inhibit_100us * 1e-4)


class PdoBus(Protocol):
    """What the PDO engine needs of the node's bus (a `sim.VectorStepSim`)."""

    @property
    def lock(self) -> AbstractContextManager[Any]: ...

    def run_after(self) -> None: ...

    def wake(self) -> None: ...


class PdoNmt(Protocol):
    """... of the node's NMT slave (a `nmt.NmtSlave`): the SYNC watchdog and EMCY."""

    def sync_timeout_s(self) -> float: ...

    def sync_watch(self, since: float | None) -> None: ...

    def emcy(self, code: int, vendor: bytes = b'', comm: bool = False) -> None: ...


class PdoNode(Protocol):
    """What the PDO engine needs of its node (a `sim.VectorStepNode`): its object dictionary
    (`_stored`, `local`), its link to the bus (`sim`, `send`, `subscribe`, `link_cut`,
    `nmt_state`), the SYNC watchdog (`nmt`) and the drive application the PDOs carry
    (`process`, `ip_on_sync`, EMCY through `nmt`)."""

    name: str
    link_cut: bool

    @property
    def local(self) -> LocalNode: ...

    @property
    def sim(self) -> PdoBus: ...

    @property
    def nmt(self) -> PdoNmt: ...

    @property
    def nmt_state(self) -> int: ...

    def _stored(self, index: int, sub: int = 0) -> Any: ...

    def send(self, cob: int, data: bytes) -> None: ...

    def subscribe(self, cob: int, handler: Callable) -> None: ...

    def unsubscribe(self, cob: int, handler: Callable) -> None: ...

    def process(self) -> None: ...

    def ip_on_sync(self, stamp_s: float) -> None: ...


class PdoEngine:
    """The PDOs of one node (`node`: see PdoNode)."""

    def __init__(self, node: PdoNode):
        self.node = node
        self.rx: list[Pdo] = []
        self.tx: list[Pdo] = []

    def load(self) -> None:
        """(Re)read the communication and mapping parameters (0x1400.., 0x1600.., 0x1800..,
        0x1A00..) and subscribe the valid PDOs."""
        node = self.node
        for pdo in self.rx + self.tx:
            if pdo.handler is not None:
                node.unsubscribe(pdo.cob_id, pdo.handler)
        self.rx, self.tx = [], []
        for n in range(4):
            for direction, comm, mapping, out in (
                    ('rx', vm.RPDO_COMMUNICATION, vm.RPDO_MAPPING, self.rx),
                    ('tx', vm.TPDO_COMMUNICATION, vm.TPDO_MAPPING, self.tx)):
                cob = node._stored(comm + n, 1)
                count = node._stored(mapping + n, 0)
                pdo = Pdo(n + 1, direction, cob_id=cob & 0x7FF,
                          valid=not cob & vm.PDO_INVALID and count > 0,
                          rtr_allowed=not cob & vm.PDO_RTR_NOT_ALLOWED,
                          trans_type=node._stored(comm + n, 2),
                          entries=tuple(vm.split_mapping_entry(node._stored(mapping + n, k))
                                        for k in range(1, count + 1)))
                if direction == 'tx':
                    pdo.inhibit_100us = node._stored(comm + n, 3)
                    pdo.event_timer_ms = node._stored(comm + n, 5)
                if pdo.valid:
                    handler = functools.partial(self._on_rpdo if direction == 'rx'
                                                else self._on_tpdo_request, pdo)
                    pdo.handler = handler
                    node.subscribe(pdo.cob_id, handler)
                out.append(pdo)

    def deadlines(self) -> list[float]:
        """When an event-driven TxPDO (254/255) is due: a change after its inhibit time, its
        event timer."""
        if self.node.nmt_state != NMT_OPERATIONAL:
            return []
        times = []
        for pdo in self.tx:
            if pdo.valid and pdo.trans_type >= 0xFE:
                if pdo.due is not None:
                    times.append(pdo.due)
                timer_due = pdo.timer_due()
                if timer_due is not None:
                    times.append(timer_due)
        return times

    def enter_operational(self) -> None:
        """The current values of the event-driven TxPDOs, once on entering OPERATIONAL."""
        for pdo in self.tx:
            if pdo.valid and pdo.trans_type >= 0xFE:
                self._send_tpdo(pdo, time.monotonic())

    def _encode(self, pdo: Pdo) -> bytes:
        data = b''
        for index, sub, bits in pdo.entries:
            data += self.node.local.get_data(index, sub)[:bits // 8]
        return data

    def _send_tpdo(self, pdo: Pdo, now: float, data: bytes | None = None) -> None:
        data = self._encode(pdo) if data is None else data
        pdo.last_data, pdo.last_sent, pdo.due = data, now, None
        self.node.send(pdo.cob_id, data)

    def _on_tpdo_request(self, pdo: Pdo, can_id: int, data: bytes, timestamp: float) -> None:
        """RTR for a TxPDO (socketcand carries it as a 0-byte data frame)."""
        if len(data) != 0:
            return
        node = self.node
        with node.sim.lock:
            if node.link_cut or node.nmt_state != NMT_OPERATIONAL or not pdo.rtr_allowed:
                return
            node.process()
            self._send_tpdo(pdo, time.monotonic(),
                            pdo.sampled if pdo.trans_type == 252 and pdo.sampled else None)

    def _on_rpdo(self, pdo: Pdo, can_id: int, data: bytes, timestamp: float) -> None:
        node = self.node
        with node.sim.lock:
            if node.link_cut or node.nmt_state != NMT_OPERATIONAL:
                return
            if len(data) > pdo.length:
                node.nmt.emcy(vm.EMCY_PDO_TOO_LONG, comm=True)     # the manual's assignment
                return
            if len(data) < pdo.length:
                node.nmt.emcy(vm.EMCY_PDO_TOO_SHORT, comm=True)
                return
            if pdo.trans_type <= 240:
                pdo.pending = bytes(data)                      # applied at the next SYNC
                return
            self._apply_rpdo(pdo, bytes(data))

    def _apply_rpdo(self, pdo: Pdo, data: bytes) -> None:
        node = self.node
        offset = 0
        for index, sub, bits in pdo.entries:
            chunk = data[offset:offset + bits // 8]
            offset += bits // 8
            try:
                node.local.set_data(index, sub, chunk)
            except SdoAbortedError as exc:
                logger.info('%s: RxPDO%d 0x%04X:%02X = %s refused: %s', node.name, pdo.number,
                            index, sub, chunk.hex(), vm.abort_text(exc.code))
        node.sim.run_after()
        node.process()
        node.sim.wake()

    def on_sync(self, now: float, stamp_s: float | None = None) -> None:
        """A SYNC received at `now`; `stamp_s` is the frame's receive stamp (interpolation
        timing; any clock, differences only), `now` when there is none."""
        node = self.node
        if node.link_cut or node.nmt_state == NMT_INITIALISING:
            return
        if node.nmt.sync_timeout_s():
            node.nmt.sync_watch(now)
        if node.nmt_state != NMT_OPERATIONAL:
            return
        for pdo in self.rx:
            if pdo.valid and pdo.pending is not None:
                data, pdo.pending = pdo.pending, None
                self._apply_rpdo(pdo, data)
        node.process()
        node.ip_on_sync(stamp_s or now)
        for pdo in self.tx:
            if not pdo.valid:
                continue
            if pdo.trans_type == 252:
                pdo.sampled = self._encode(pdo)
            elif pdo.trans_type == 0:
                data = self._encode(pdo)
                if data != pdo.last_data:
                    self._send_tpdo(pdo, now, data)
            elif pdo.trans_type <= 240:
                pdo.sync_count += 1
                if pdo.sync_count >= pdo.trans_type:
                    pdo.sync_count = 0
                    self._send_tpdo(pdo, now)

    def tpdo_check(self, now: float) -> None:
        """Event-driven TxPDOs (254/255): on change, spaced by the inhibit time; event timer."""
        if self.node.link_cut or self.node.nmt_state != NMT_OPERATIONAL:
            return
        for pdo in self.tx:
            if not pdo.valid or pdo.trans_type < 0xFE:
                continue
            inhibit_s = pdo.inhibit_100us * 1e-4
            data = self._encode(pdo)
            if data != pdo.last_data:
                if now >= pdo.last_sent + inhibit_s:
                    self._send_tpdo(pdo, now, data)
                else:
                    pdo.due = pdo.last_sent + inhibit_s
                continue
            # A change that went back within the inhibit time leaves nothing to send: a `due`
            # kept in the past would make deadlines() return it and the cycle loop spin.
            pdo.due = None
            due = pdo.timer_due()
            if due is not None and now >= due:
                period_s = due - pdo.last_sent
                self._send_tpdo(pdo, now, data)
                if now - due < period_s:
                    pdo.last_sent = due       # a late wake-up does not shift the timer's phase
