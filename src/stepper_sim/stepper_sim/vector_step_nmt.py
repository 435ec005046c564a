"""Vector Step simulator, CANopen NMT slave and error control (CiA 301): a mixin of VectorStepNode.

Boot-up after power-on and NMT reset node/communication (reboot delay, 10 ms between boot-up and
the first heartbeat), NMT commands, heartbeat producer (0x1017, sent by VectorStepNode.tick), node
guarding (a 0-byte frame on 0x700+ID counts as the RTR socketcand cannot carry), life guarding and
consumer heartbeat (0x1016), the EMCY producer (0x1014, inhibit time 0x1015) and the SYNC watchdog
(0x1006: no SYNC for that long is the drive alarm "Mancanza Sync", Ralarm32 bit 18).
"""

from __future__ import annotations

import logging
import struct
import time
from typing import Callable

from stepper_drivers.vendors import vector_step_map as vm


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


class NmtSlave:
    """NMT, error control, EMCY and the SYNC watchdog of one node (state: VectorStepNode)."""

    def _reset_communication(self) -> None:
        for index in [i for i in self.local.data_store if 0x1000 <= i <= 0x1FFF]:
            del self.local.data_store[index]
        self.guard_toggle = 0
        self.guard_seen = None
        self.consumer_seen.clear()
        self._sync_watch(None)            # 0x1006 is back to 0: not watched

    def _sync_watch(self, since: float | None) -> None:
        """(Re)start the SYNC watchdog from `since` (a SYNC, a write of 0x1006); None: off. A
        SYNC or a new 0x1006 removes the alarm's cause (it stays latched in Ralarm32)."""
        self.sync_at = since
        self.sync_suspect_at: float | None = None
        self.sync_error = False
        self.alarm_causes &= ~RALARM_MISSING_SYNC

    def _sync_timeout_s(self) -> float:
        return self._stored(vm.COMMUNICATION_CYCLE_PERIOD) / 1e6

    def _sync_deadline(self) -> float | None:
        timeout_s = self._sync_timeout_s()
        if not timeout_s or self.sync_at is None:
            return None
        if self.sync_suspect_at is not None:
            return self.sync_suspect_at + SYNC_CONFIRM_S
        return self.sync_at + timeout_s

    def _check_sync(self, now: float) -> None:
        deadline = self._sync_deadline()
        if deadline is None or now < deadline:
            return
        if self.sync_suspect_at is None:
            self.sync_suspect_at = now       # confirmed at the next cycle (SYNC_CONFIRM_S)
            return
        logger.info('%s: no SYNC for %.3f s (0x1006 = %d us): alarm "missing SYNC"', self.name,
                    now - self.sync_at, self._stored(vm.COMMUNICATION_CYCLE_PERIOD))
        self.sync_at = self.sync_suspect_at = None        # one alarm per loss
        self.sync_error = True                            # Rcansts / LED "Sync error"
        self.raise_alarm(RALARM_MISSING_SYNC)

    def attach(self) -> None:
        network = self.sim.network
        self.local.network = network
        self.local.sdo.network = network
        self._subscribe(0x000, self._on_nmt)
        self._subscribe(0x700 + self.id, self._on_guard)

    def detach(self) -> None:
        for cob, handler in self._subscriptions:
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass
        self._subscriptions.clear()

    def _subscribe(self, cob: int, handler: Callable) -> None:
        self.sim.network.subscribe(cob, handler)
        self._subscriptions.append((cob, handler))

    def _unsubscribe(self, cob: int, handler: Callable) -> None:
        if (cob, handler) in self._subscriptions:
            self._subscriptions.remove((cob, handler))
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass

    def boot(self, delay_s: float) -> None:
        """Go silent, then boot after delay_s (power-on / reset)."""
        self.nmt_state = NMT_INITIALISING
        self.heartbeat_due = None
        self.boot_at = time.monotonic() + delay_s
        self.sim.wake()

    def _finish_boot(self, now: float) -> None:
        self.boot_at = None
        for cob, handler in [s for s in self._subscriptions if s[1] == self._on_sdo]:
            self._unsubscribe(cob, handler)
        self.sdo_rx_cob, self.sdo_tx_cob = 0x600 + self.id, 0x580 + self.id
        self.local.sdo.rx_cobid, self.local.sdo.tx_cobid = self.sdo_rx_cob, self.sdo_tx_cob
        self._subscribe(self.sdo_rx_cob, self._on_sdo)
        self._load_pdos()
        self._load_consumers()
        self._send(0x700 + self.id, b'\x00')            # boot-up
        self.nmt_state = NMT_PRE_OPERATIONAL
        self.heartbeat_due = now + BOOTUP_TO_HEARTBEAT_S
        logger.info('%s (node %d): boot-up, PRE-OPERATIONAL', self.name, self.id)

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.id):
            return
        with self.sim.lock:
            if self.link_cut or self.nmt_state == NMT_INITIALISING:
                return
            command = data[0]
            if command == 0x01:
                self._enter_nmt(NMT_OPERATIONAL)
            elif command == 0x02:
                self._enter_nmt(NMT_STOPPED)
            elif command == 0x80:
                self._enter_nmt(NMT_PRE_OPERATIONAL)
            elif command == 0x81:
                logger.info('%s: NMT reset node', self.name)
                self._power_on_state()
                self.boot(self.sim.reboot_delay_s)
            elif command == 0x82:
                logger.info('%s: NMT reset communication', self.name)
                self._reset_communication()
                self.boot(self.sim.reboot_delay_s)

    def _enter_nmt(self, state: int) -> None:
        old, self.nmt_state = self.nmt_state, state
        if state != old:
            logger.info('%s: NMT %s', self.name, NMT_NAMES[state])
        if state == NMT_OPERATIONAL and old != NMT_OPERATIONAL:
            for pdo in self.tx:                 # current values once on entering OPERATIONAL
                if pdo.valid and pdo.trans_type >= 0xFE:
                    self._send_tpdo(pdo, time.monotonic())

    def _on_guard(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Node guarding: an RTR (a 0-byte frame over socketcand) on 0x700+ID."""
        if len(data) != 0:
            return
        with self.sim.lock:
            if self.link_cut or self.nmt_state == NMT_INITIALISING:
                return
            self.guard_seen = time.monotonic()
            self._send(0x700 + self.id, bytes([self.guard_toggle | self.nmt_state]))
            self.guard_toggle ^= 0x80

    def _load_consumers(self) -> None:
        for cob, handler in [s for s in self._subscriptions if s[1] == self._on_consumer]:
            self._unsubscribe(cob, handler)
        self.consumers: dict[int, float] = {}
        for sub in (1, 2):
            entry = self._stored(vm.CONSUMER_HEARTBEAT_TIME, sub)
            node, time_ms = (entry >> 16) & 0xFF, entry & 0xFFFF
            if node and time_ms:
                self.consumers[node] = time_ms / 1000.0
                self._subscribe(0x700 + node, self._on_consumer)

    def _on_consumer(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.sim.lock:
            self.consumer_seen[can_id - 0x700] = time.monotonic()

    def _life_time_s(self) -> float:
        return self._stored(vm.GUARD_TIME) * self._stored(vm.LIFE_TIME_FACTOR) / 1000.0

    def emcy(self, code: int, vendor: bytes = b'', comm: bool = False) -> None:
        """Send an EMCY [PRE-DEFINED ERROR FIELD]; record it in 0x1003/0x603F unless a reset."""
        if code != vm.EMCY_NO_ERROR:
            self.comm_error = self.comm_error or comm
            extra = int.from_bytes(vendor[:2].ljust(2, b'\0'), 'little')
            self.history.insert(0, code | extra << 16)     # newest at sub 1
            del self.history[vm.ERROR_HISTORY_DEPTH:]
            self.error_code = code
        frame = struct.pack('<HB', code, self.error_register()) + vendor[:5].ljust(5, b'\0')
        cob = self._stored(vm.COB_ID_EMCY)
        if cob & vm.PDO_INVALID:
            return
        inhibit_s = self._stored(vm.INHIBIT_TIME_EMCY) * 1e-4
        now = time.monotonic()
        if self.emcy_queue or now < self.last_emcy_at + inhibit_s:
            self.emcy_queue.append(frame)
            self.sim.wake()
        else:
            self.last_emcy_at = now
            self._send(cob & 0x7FF, frame)
        logger.info('%s: EMCY 0x%04X %s', self.name, code, vm.emcy_text(code, vendor))

    def _send(self, cob: int, data: bytes) -> None:
        if self.link_cut:
            return
        self.sim.send(cob, data)
