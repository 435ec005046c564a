"""Vector Step simulator, CANopen NMT slave and error control (CiA 301): a part of VectorStepNode.

Boot-up after power-on and NMT reset node/communication (reboot delay, 10 ms between boot-up and
the first heartbeat), NMT commands, heartbeat producer (0x1017, on VectorStepNode.tick), node
guarding (a 0-byte frame on 0x700+ID counts as the RTR socketcand cannot carry), life guarding and
consumer heartbeat (0x1016), the EMCY producer (0x1014, inhibit time 0x1015) and the SYNC watchdog
(0x1006: no SYNC for that long is the drive alarm "Mancanza Sync", Ralarm32 bit 18).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
import logging
import struct
import time
from typing import Any, Callable, Protocol

from canopen import LocalNode
from stepper_drivers.vendors.vector_step import regmap as vm

logger = logging.getLogger(__name__)

# NMT states (heartbeat byte values, CiA 301)
NMT_INITIALISING = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_NAMES = {NMT_INITIALISING: 'INITIALISING', NMT_STOPPED: 'STOPPED',
             NMT_OPERATIONAL: 'OPERATIONAL', NMT_PRE_OPERATIONAL: 'PRE-OPERATIONAL'}
# transports.md A5.3.6: a heartbeat right behind the boot-up hides it from
# NmtMaster.wait_for_bootup()
BOOTUP_TO_HEARTBEAT_S = 0.010
# A missing SYNC is confirmed this much later: a simulator process the machine starved for a
# while would otherwise see its own lateness (SYNCs still queued in its socket) as a lost SYNC.
SYNC_CONFIRM_S = 0.02
RALARM_MISSING_SYNC = 1 << 18        # Ralarm32 bit 18 "Mancanza Sync (CANopen o EtherCAT)"


class NmtBus(Protocol):
    """What the NMT slave needs of the node's bus (a `sim.VectorStepSim`)."""

    reboot_delay_s: float

    @property
    def lock(self) -> AbstractContextManager[Any]: ...

    def wake(self) -> None: ...


class NmtSdo(Protocol):
    """... of the node's SDO server (a `sdo.SdoServer`): started at boot-up."""

    def start(self) -> None: ...


class NmtPdo(Protocol):
    """... of the node's PDO engine (a `pdo.PdoEngine`): loaded at boot-up, sent on entering
    OPERATIONAL."""

    def load(self) -> None: ...

    def enter_operational(self) -> None: ...


class NmtNode(Protocol):
    """What the NMT slave needs of its node (a `sim.VectorStepNode`): its object dictionary
    (`_stored`, `local`), its link to the bus (`sim`, `send`, `subscribe`, `link_cut`), the
    parts started at boot-up (`sdo`, `pdo`) and the drive application this resets and reports
    for (`_power_on_state`, `raise_alarm`, the error history and `error_register`)."""

    name: str
    id: int
    link_cut: bool
    alarm_causes: int
    comm_error: bool
    history: list[int]
    error_code: int

    @property
    def local(self) -> LocalNode: ...

    @property
    def sim(self) -> NmtBus: ...

    @property
    def sdo(self) -> NmtSdo: ...

    @property
    def pdo(self) -> NmtPdo: ...

    def _stored(self, index: int, sub: int = 0) -> Any: ...

    def send(self, cob: int, data: bytes) -> None: ...

    def subscribe(self, cob: int, handler: Callable) -> None: ...

    def unsubscribe_all(self, handler: Callable) -> None: ...

    def raise_alarm(self, bits: int) -> None: ...

    def error_register(self) -> int: ...

    def _power_on_state(self) -> None: ...


class NmtSlave:
    """NMT, error control, EMCY and the SYNC watchdog of one node (`node`: see NmtNode)."""

    def __init__(self, node: NmtNode):
        self.node = node
        self.state = NMT_INITIALISING
        self.boot_at: float | None = None
        self.heartbeat_due: float | None = None
        self.guard_toggle = 0
        self.guard_seen: float | None = None
        self.consumers: dict[int, float] = {}     # node-ID -> heartbeat consumer time (0x1016)
        self.consumer_seen: dict[int, float] = {}
        self.last_emcy_at = -1e9
        self.emcy_queue: list[bytes] = []
        self.sync_at: float | None = None   # last SYNC (or 0x1006 write) the watchdog counts from
        self.sync_suspect_at: float | None = None
        self.sync_error = False

    def power_on(self) -> None:
        """Error control and EMCY state after power-on or NMT reset node (0x1006 not watched)."""
        self.last_emcy_at = -1e9
        self.emcy_queue = []
        self.guard_toggle = 0
        self.guard_seen = None
        self.consumer_seen = {}
        self.sync_watch(None)

    def reset_communication(self) -> None:
        data_store = self.node.local.data_store
        for index in [i for i in data_store if 0x1000 <= i <= 0x1FFF]:
            del data_store[index]
        self.guard_toggle = 0
        self.guard_seen = None
        self.consumer_seen.clear()
        self.sync_watch(None)             # 0x1006 is back to 0: not watched

    def sync_watch(self, since: float | None) -> None:
        """(Re)start the SYNC watchdog from `since` (a SYNC, a write of 0x1006); None: off. A
        SYNC or a new 0x1006 removes the alarm's cause (it stays latched in Ralarm32)."""
        self.sync_at = since
        self.sync_suspect_at = None
        self.sync_error = False
        self.node.alarm_causes &= ~RALARM_MISSING_SYNC

    def sync_timeout_s(self) -> float:
        return self.node._stored(vm.COMMUNICATION_CYCLE_PERIOD) / 1e6

    def sync_deadline(self) -> float | None:
        timeout_s = self.sync_timeout_s()
        if not timeout_s or self.sync_at is None:
            return None
        if self.sync_suspect_at is not None:
            return self.sync_suspect_at + SYNC_CONFIRM_S
        return self.sync_at + timeout_s

    def check_sync(self, now: float) -> None:
        deadline = self.sync_deadline()
        if deadline is None or now < deadline:
            return
        if self.sync_suspect_at is None:
            self.sync_suspect_at = now       # confirmed at the next cycle (SYNC_CONFIRM_S)
            return
        logger.info('%s: no SYNC for %.3f s (0x1006 = %d us): alarm "missing SYNC"',
                    self.node.name, now - self.sync_at,
                    self.node._stored(vm.COMMUNICATION_CYCLE_PERIOD))
        self.sync_at = self.sync_suspect_at = None        # one alarm per loss
        self.sync_error = True                            # Rcansts / LED "Sync error"
        self.node.raise_alarm(RALARM_MISSING_SYNC)

    def deadlines(self) -> list[float]:
        """When the heartbeat, a queued EMCY, life guarding or a consumer heartbeat is due."""
        node = self.node
        times = []
        if node._stored(vm.PRODUCER_HEARTBEAT_TIME) and self.heartbeat_due is not None:
            times.append(self.heartbeat_due)
        if self.emcy_queue:
            times.append(self.last_emcy_at + node._stored(vm.INHIBIT_TIME_EMCY) * 1e-4)
        life = self.life_time_s()
        if life and self.guard_seen is not None:
            times.append(self.guard_seen + life)
        for node_id, timeout in self.consumers.items():
            seen = self.consumer_seen.get(node_id)
            if seen is not None:
                times.append(seen + timeout)
        return times

    def heartbeat(self, now: float) -> None:
        """The heartbeat producer (0x1017), when it is due."""
        node = self.node
        period_ms = node._stored(vm.PRODUCER_HEARTBEAT_TIME)
        if period_ms and self.heartbeat_due is not None and now >= self.heartbeat_due:
            node.send(0x700 + node.id, bytes([self.state]))
            self.heartbeat_due += period_ms / 1000.0
            if self.heartbeat_due <= now:          # late (or just switched on): re-phase
                self.heartbeat_due = now + period_ms / 1000.0

    def error_control(self, now: float) -> None:
        """A queued EMCY once its inhibit time is over; life guarding and consumer heartbeat."""
        node = self.node
        if self.emcy_queue and now >= self.last_emcy_at + \
                node._stored(vm.INHIBIT_TIME_EMCY) * 1e-4:
            cob = node._stored(vm.COB_ID_EMCY) & 0x7FF
            self.last_emcy_at = now
            node.send(cob, self.emcy_queue.pop(0))
        life = self.life_time_s()
        if life and self.guard_seen is not None and now > self.guard_seen + life:
            self.guard_seen = None               # one event per loss
            logger.info('%s: life guarding: no guard request within %.3f s', node.name, life)
            self.emcy(vm.EMCY_ERROR_CONTROL, comm=True)
        for node_id, timeout in self.consumers.items():
            seen = self.consumer_seen.get(node_id)
            if seen is not None and now > seen + timeout:
                del self.consumer_seen[node_id]
                logger.info('%s: heartbeat of node %d lost', node.name, node_id)
                self.emcy(vm.EMCY_ERROR_CONTROL, bytes([node_id]), comm=True)

    def boot(self, delay_s: float) -> None:
        """Go silent, then boot after delay_s (power-on / reset)."""
        self.state = NMT_INITIALISING
        self.heartbeat_due = None
        self.boot_at = time.monotonic() + delay_s
        self.node.sim.wake()

    def finish_boot(self, now: float) -> None:
        node = self.node
        self.boot_at = None
        node.sdo.start()
        node.pdo.load()
        self.load_consumers()
        node.send(0x700 + node.id, b'\x00')            # boot-up
        self.state = NMT_PRE_OPERATIONAL
        self.heartbeat_due = now + BOOTUP_TO_HEARTBEAT_S
        logger.info('%s (node %d): boot-up, PRE-OPERATIONAL', node.name, node.id)

    def on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        node = self.node
        if len(data) < 2 or data[1] not in (0, node.id):
            return
        with node.sim.lock:
            if node.link_cut or self.state == NMT_INITIALISING:
                return
            command = data[0]
            if command == 0x01:
                self._enter(NMT_OPERATIONAL)
            elif command == 0x02:
                self._enter(NMT_STOPPED)
            elif command == 0x80:
                self._enter(NMT_PRE_OPERATIONAL)
            elif command == 0x81:
                logger.info('%s: NMT reset node', node.name)
                node._power_on_state()
                self.boot(node.sim.reboot_delay_s)
            elif command == 0x82:
                logger.info('%s: NMT reset communication', node.name)
                self.reset_communication()
                self.boot(node.sim.reboot_delay_s)

    def _enter(self, state: int) -> None:
        old, self.state = self.state, state
        if state != old:
            logger.info('%s: NMT %s', self.node.name, NMT_NAMES[state])
        if state == NMT_OPERATIONAL and old != NMT_OPERATIONAL:
            self.node.pdo.enter_operational()

    def on_guard(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Node guarding: an RTR (a 0-byte frame over socketcand) on 0x700+ID."""
        if len(data) != 0:
            return
        node = self.node
        with node.sim.lock:
            if node.link_cut or self.state == NMT_INITIALISING:
                return
            self.guard_seen = time.monotonic()
            node.send(0x700 + node.id, bytes([self.guard_toggle | self.state]))
            self.guard_toggle ^= 0x80

    def load_consumers(self) -> None:
        node = self.node
        node.unsubscribe_all(self._on_consumer)
        self.consumers = {}
        for sub in (1, 2):
            entry = node._stored(vm.CONSUMER_HEARTBEAT_TIME, sub)
            node_id, time_ms = (entry >> 16) & 0xFF, entry & 0xFFFF
            if node_id and time_ms:
                self.consumers[node_id] = time_ms / 1000.0
                node.subscribe(0x700 + node_id, self._on_consumer)

    def _on_consumer(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.node.sim.lock:
            self.consumer_seen[can_id - 0x700] = time.monotonic()

    def life_time_s(self) -> float:
        return self.node._stored(vm.GUARD_TIME) * self.node._stored(vm.LIFE_TIME_FACTOR) / 1000.0

    def emcy(self, code: int, vendor: bytes = b'', comm: bool = False) -> None:
        """Send an EMCY [PRE-DEFINED ERROR FIELD]; record it in 0x1003/0x603F unless a reset."""
        node = self.node
        if code != vm.EMCY_NO_ERROR:
            node.comm_error = node.comm_error or comm
            extra = int.from_bytes(vendor[:2].ljust(2, b'\0'), 'little')
            node.history.insert(0, code | extra << 16)     # newest at sub 1
            del node.history[vm.ERROR_HISTORY_DEPTH:]
            node.error_code = code
        frame = struct.pack('<HB', code, node.error_register()) + vendor[:5].ljust(5, b'\0')
        cob = node._stored(vm.COB_ID_EMCY)
        if cob & vm.PDO_INVALID:
            return
        inhibit_s = node._stored(vm.INHIBIT_TIME_EMCY) * 1e-4
        now = time.monotonic()
        if self.emcy_queue or now < self.last_emcy_at + inhibit_s:
            self.emcy_queue.append(frame)
            node.sim.wake()
        else:
            self.last_emcy_at = now
            node.send(cob & 0x7FF, frame)
        logger.info('%s: EMCY 0x%04X %s', node.name, code, vm.emcy_text(code, vendor))
