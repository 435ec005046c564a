"""The Vector Step's process image: what its TxPDOs carry, coherent per statusword.

`ProcessImage` is a base of `drive.VectorStepDrive`, split from it for size: the two work on one
record (the drive's link, bus and node-ID), and only VectorStepDrive is made. It holds the PDO
side of a node, as ros2_canopen keeps the PDO/SDO image apart from the CiA 402 state machine:
- at every boot, the PDO set of regmap's DRIVER_RPDOS/DRIVER_TPDOS written with the manual's
  mapping procedure [COME MAPPARE UN PDO] (`_configure_pdos`) and the cache seeded by SDO
  (`_seed`);
- the decoding of each TxPDO on the bus' receive thread into canopen's BaseNode402 cache
  (tpdo_values, `_on_tpdo`), with the statusword of TxPDO1 as the newest;
- burst coherence: the wait for the other TxPDOs a statusword change sends, and the SDO reads
  of a late one's objects (`_wait_for_burst`); the position of a standing axis read by SDO
  after its statusword (`_standing_position`);
- snapshot vouching: read_state gives the last snapshot again while nothing it was made of
  changed (`unchanged_until`, `_snapshot_key`).

Not here: the NMT boot, identity and liveness checks (node.py), the controlword by RxPDO and
the CiA 402 state a snapshot decodes from the image (drive.py), the modes (modes.py). No rclpy.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

from ...contract.drive import DriveState, HomingState, LinkError, Operation
from . import regmap as vm

# the vendor's one logger (the package's name, as before the package was split into modules)
logger = logging.getLogger(__package__)

# unchanged_until vouches for at most this long: the bus' receive thread is looked at again
QUIET_CHECK_S = 0.1
# A statusword change goes out in every TxPDO back to back; the other drives' bursts, SYNC and
# heartbeats may come in between. The wire time of one such round is the bound of the wait for a
# coherent snapshot: FRAME_BITS per frame (11-bit identifier, 8 data bytes, worst-case stuff
# bits; ISO 11898-1), one frame per TxPDO and drive on the bus, at the bus' bit rate (10 kbit/s:
# 13.5 ms per frame [LAYER FISICO]), plus BURST_SLACK_S for the receive thread.
FRAME_BITS = 135
BURST_SLACK_S = 0.02
# The TxPDOs that tpdo_inhibit_ms spaces out: the two whose values change all through a motion
# (position, velocity); TxPDO1 and TxPDO4 still carry a statusword change at once.
INHIBITED_TPDOS = (2, 3)
POSITION_TPDO = next(n for n, entries in enumerate(vm.DRIVER_TPDOS, 1)
                     if any(index == vm.POSITION_ACTUAL_VALUE for index, _, _ in entries))


class ProcessImage:
    """The TxPDO cache of one Vector Step and the snapshots read from it (see the module).

    Uses the drive's record: `link` (RemoteDrive), `can` (CanBus), `node_id`, the TxPDO timing
    (`event_timer_ms`, `inhibit_100us`), the heartbeat (`heartbeat_ms`, `heartbeat_timeout_s`,
    `_connected_at`) and, in a snapshot's key, the commanded controlword and homing. Its own
    state is set by `_init_image`; `read_state` calls the drive's `_check_alive` (node.py) and
    `_read_state_steps` (drive.py).
    """

    def _init_image(self) -> None:
        """The image's state (VectorStepDrive.__init__, once the node-ID is known)."""
        self._pdo_statusword: dict[int, int] = {}    # COB-ID -> statusword of its last TxPDO
        # (newest TxPDO1 statusword, when it came, its number): every change of TxPDO1's
        # statusword gets the next number, never reset, so a number names one of them even
        # where the drive comes back to an earlier value (the end of a move is the standstill
        # before it again)
        self._statusword_seen = (0, 0.0, 0)
        # what the receive thread writes (_on_tpdo) and a snapshot reads as one (the statusword
        # and its number, the cache, the standing position)
        self._rx_lock = threading.Lock()
        # (statusword number, 0x6064): the position of a standing axis, read by SDO after that
        # statusword came (_standing_position); None: not read since the last change
        self._standing: tuple[int, int] | None = None
        self._position_cob = vm.PDO_COB_BASES_TX[POSITION_TPDO - 1] + self.node_id
        self._state_cob = vm.PDO_COB_BASES_TX[0] + self.node_id      # TxPDO1
        # (reception, position): the last TxPDO2, or the SDO read of a late one
        self._position_rx: tuple[float, int] | None = None
        self._tpdo_entries: dict[int, tuple] = {}     # COB-ID: what that TxPDO maps
        self._tpdo_layouts: dict[int, tuple] = {}     # COB-ID: (struct, indexes) to store it
        self._sdo_read: set[int] = set()  # TxPDOs whose objects _wait_for_burst read by SDO
        self._snapshot: tuple[tuple | None, DriveState | None] = (None, None)  # (key, state)
        # (link.changes, controlword, homing, the snapshot) under which read_state gives the
        # snapshot again without a look at the cache, until _alive_until (unchanged_until); None:
        # look
        self._quiet: tuple[int, int | None, HomingState, DriveState] | None = None
        self._alive_until = 0.0
        self._burst_given_up: int | None = None   # number of the statusword whose wait gave up

    def _values(self) -> dict[int, Any]:
        node = self.link.node
        if node is None:
            raise LinkError(f'{self._prefix()}not connected')
        return node.tpdo_values

    def _read_statusword(self) -> int:
        """The newest statusword: TxPDO1's (see _on_tpdo)."""
        self.can.check()
        sw = self._pdo_statusword.get(self._state_cob)
        return int(self._values().get(vm.STATUSWORD, 0)) if sw is None else sw

    # ------------------------------------------------------------------ PDO set and TxPDOs
    def _configure_pdos(self) -> Operation[None]:
        for number, entries in enumerate(vm.DRIVER_RPDOS, 1):
            yield from self.link.configure_pdo('rx', number, entries)
            yield 0.0
        for number in range(len(vm.DRIVER_RPDOS) + 1, 5):      # the others off
            yield from self.link.configure_pdo('rx', number, ())
            yield 0.0
        for number, entries in enumerate(vm.DRIVER_TPDOS, 1):
            yield 0.0
            timer = self.event_timer_ms if number == 2 else 0
            yield from self.link.configure_pdo(
                'tx', number, entries, 0xFE, event_timer_ms=timer,
                inhibit_time_100us=self.inhibit_100us if number in INHIBITED_TPDOS else 0)
        node = self.link.node
        node.setup_pdos(upload=False)
        self._tpdo_entries, self._tpdo_layouts = {}, {}
        for number in range(1, len(vm.DRIVER_TPDOS) + 1):
            pdo = node.tpdo[number]
            entries = vm.DRIVER_TPDOS[number - 1]
            self._tpdo_entries[pdo.cob_id] = entries
            self._tpdo_layouts[pdo.cob_id] = (self.link.pdo_struct(entries),
                                              tuple(index for index, _, _ in entries))
        self.link.watch_tpdos(self._on_tpdo)

    def _on_tpdo(self, cob: int, data: bytearray) -> None:
        """(receive thread) Store what a TxPDO carries in the cache (tpdo_values).

        Every DRIVER_TPDOS mapping starts with the statusword, and a change of it sends all
        four, TxPDO1 first: TxPDO1 has the node's lowest COB-ID, so it also overtakes the
        TxPDO2..4 of the state before when they still wait for the bus (a slow or busy bus; a
        drive with several transmit buffers). So the statusword of TxPDO1 is the newest: the
        cache keeps it, and the others' only tells whether their burst is complete. A TxPDO2..4
        of an older state is still newer than the cache, except after _wait_for_burst read its
        objects by SDO for the newest state: then it is dropped until its own TxPDO of that
        state comes.

        Not so the position of a standing axis: a TxPDO2 with the newest statusword may still
        be older than it (the standstill before a move shorter than the bus' delay has the
        statusword of its end). Once _standing_position has read it by SDO for that statusword,
        a TxPDO2 leaves it as read; one that shows another position with that statusword has
        it read again at the next poll (it is older, or the axis was moved: an encoder)."""
        layout, indexes = self._tpdo_layouts[cob]
        fields = layout.unpack_from(data)     # (the bus checked the frame's length)
        sw = fields[0]
        now = time.monotonic()
        with self._rx_lock:
            self._pdo_statusword[cob] = sw
            newest = self._pdo_statusword.get(self._state_cob, sw)
            if cob == self._state_cob:
                if sw != self._statusword_seen[0]:
                    self._statusword_seen = (sw, now, self._statusword_seen[2] + 1)
                    self._sdo_read.clear()
            elif cob in self._sdo_read:
                if sw != newest:
                    return
                self._sdo_read.discard(cob)
            values = self._values()
            standing = self._standing
            if cob == self._position_cob and standing is not None and \
                    standing[0] == self._statusword_seen[2]:
                if sw == newest and fields[1] != standing[1]:
                    self._standing = None
                fields = (sw, standing[1])        # statusword, then the position (i32)
            elif cob == self._position_cob:
                self._position_rx = (now, fields[1])
            for index, value in zip(indexes, fields):
                values[index] = value
            values[vm.STATUSWORD] = newest

    def _coherent(self) -> bool:
        return len(set(self._pdo_statusword.values())) <= 1

    def _wait_for_burst(self) -> Operation[None]:
        """A statusword change goes out in every TxPDO, back to back. Until the last of those
        frames is in, the others hold values from before the change (velocity, Rstsflg's homed
        bit, the position after homing): wait for them, as long as the bus needs to carry them
        at its bit rate, so one snapshot is coherent."""
        newest, since, number = self._statusword_seen
        if self._coherent() or number == self._burst_given_up:
            return
        bound_s = len(vm.DRIVER_TPDOS) * max(self.can.drive_count, 1) * FRAME_BITS \
            / self.can.bitrate + BURST_SLACK_S + self.inhibit_100us * 1e-4
        if not (yield from self.link.wait(self._coherent, since + bound_s - time.monotonic())):
            # A frame of the burst is late (a slow or busy bus: other drives' lower COB-IDs go
            # first) or lost: what the late TxPDOs carry is read by SDO instead, so this
            # snapshot holds nothing older than its statusword (a position from before a
            # "target reached" would end a move_to at the wrong place). Then no poll waits
            # again until the next change.
            self._burst_given_up = number
            late = sorted(c for c, sw in self._pdo_statusword.items() if sw != newest)
            logger.info('%sTxPDO burst of statusword 0x%04X incomplete after %.3f s (late: %s):'
                        ' reading their objects by SDO', self._prefix(), newest, bound_s,
                        ', '.join(f'0x{c:03X}' for c in late))
            values = self._values()
            for cob in late:
                for index, sub, _bits in self._tpdo_entries.get(cob, ()):
                    if index == vm.STATUSWORD or (index == vm.POSITION_ACTUAL_VALUE and
                                                  self._standing_for(number)):
                        continue
                    yield 0.0
                    value = self.link.read(index, sub)
                    with self._rx_lock:
                        if index == vm.POSITION_ACTUAL_VALUE and \
                                not newest & vm.SW_BIT_MOTOR_MOVING and \
                                self._stand(number, int(value)):
                            continue            # read after the statusword of a standstill
                        # the late TxPDO itself came during the upload: its values are as new
                        # (an older upload written over them would stay until the next change)
                        if self._pdo_statusword.get(cob) != newest:
                            values[index] = value
                            if index == vm.POSITION_ACTUAL_VALUE:
                                # true when its answer came, not at every later poll
                                self._position_rx = (time.monotonic(), int(value))
                with self._rx_lock:
                    if self._statusword_seen[2] == number and \
                            self._pdo_statusword.get(cob) != newest:
                        self._sdo_read.add(cob)   # its frames of older states are older

    def _standing_for(self, number: int) -> bool:
        """The position of statusword `number` (a standstill) was read after it came."""
        standing = self._standing
        return standing is not None and standing[0] == number

    def _stand(self, number: int, position: int) -> bool:
        """(_rx_lock held) 0x6064 read by SDO after statusword `number` came, which says the
        axis stands: its position while it stands, unless a newer statusword came meanwhile
        (the answer may be of that one, moving again)."""
        if self._statusword_seen[2] != number:
            return False
        self._standing = (number, position)
        self._values()[vm.POSITION_ACTUAL_VALUE] = position
        self._position_rx = (time.monotonic(), position)
        return True

    def _standing_position(self) -> Operation[None]:
        """The position of a standing axis (statusword bit 8 "Motor moving" off, [STATUSWORD]),
        read by SDO after the statusword came, once per statusword (and command, see
        _write_controlword): the position a move_to, a homing or a trajectory ends on.

        No TxPDO can tell it: a standing drive repeats one statusword, so the TxPDO2 of the
        standstill before a move that is shorter than the bus' delay (a slow or busy bus:
        TxPDO2..4 come after TxPDO1) carries the statusword of the move's end with the
        position the move started from, and the order in which frames come in tells nothing
        of when they were sampled. An SDO answer does: the drive sends it after the TxPDO1 of
        the statusword it has then (TxPDO1 is sent at the change, and its COB-ID wins the
        arbitration against the answer's), so while no newer TxPDO1 came before the answer,
        the answer is of that statusword (`_stand`)."""
        sw, _, number = self._statusword_seen
        if sw & vm.SW_BIT_MOTOR_MOVING or self._standing_for(number):
            return
        yield 0.0
        value = int(self.link.read(vm.POSITION_ACTUAL_VALUE, 0))
        with self._rx_lock:
            self._stand(number, value)

    def _seed(self) -> Operation[None]:
        """Current values by SDO, so the cache is right before the first TxPDO arrives (the
        position 0x6064 after the statusword 0x6041: a standing axis' position is known)."""
        values = self._values()
        for index, sub, _bits in sorted({e for pdo in vm.DRIVER_TPDOS for e in pdo}):
            yield 0.0
            values[index] = self.link.read(index, sub)
        sw = int(values[vm.STATUSWORD])
        with self._rx_lock:
            self._pdo_statusword = {pdo.cob_id: sw for pdo in self.link.node.tpdo.values()
                                    if pdo.enabled}
            number = self._statusword_seen[2] + 1
            self._statusword_seen = (sw, time.monotonic(), number)
            self._burst_given_up = None
            self._sdo_read.clear()
            self._position_rx = None
            self._standing = None if sw & vm.SW_BIT_MOTOR_MOVING else \
                (number, int(values[vm.POSITION_ACTUAL_VALUE]))

    # ------------------------------------------------------------------ snapshot vouching
    def read_state(self) -> DriveState | Operation[DriveState]:
        """The state from the TxPDO cache. The last snapshot again while nothing it was made of
        changed: an idle drive's TxPDO2 event timer repeats the same bytes, which the link does
        not count as a change (RemoteDrive.changes). While the link counted no change, this
        driver commanded nothing (controlword, homing) and the heartbeat's deadline is ahead,
        the poll is that look (`unchanged_until`); else the liveness checks and the snapshot key.
        Step-wise only while a burst is incomplete, a fault is read, a warning is due, or the
        position of an axis that stands is read (_standing_position)."""
        state = self._snapshot[1]
        if state is not None and self.unchanged_until(state):
            return state
        self._quiet = None
        changes = self.link.changes              # before what it vouches for
        self._check_alive()
        with self._rx_lock:
            key = self._snapshot_key()
        if key == self._snapshot[0]:
            self._quiet = (changes, self.cia.controlword, self._homing, self._snapshot[1])
            self._alive_until = self._heartbeat_deadline()
            return self._snapshot[1]
        return self._read_state_steps()

    def unchanged_until(self, state: DriveState) -> float:
        """While the link counted no change, the controlword and homing are as the snapshot
        had them, and the bus receives: until the heartbeat's deadline, and at most
        QUIET_CHECK_S ahead (a dead receive thread shows only here when the heartbeat is off)."""
        if self._quiet != (self.link.changes, self.cia.controlword, self._homing, state) \
                or not self.can.receiving:       # the bus open, its receive thread alive
            return 0.0
        now = time.monotonic()
        if now >= self._alive_until:
            self._alive_until = self._heartbeat_deadline()    # from the last heartbeat
            if now >= self._alive_until:
                return 0.0
        return min(self._alive_until, now + QUIET_CHECK_S)

    def _heartbeat_deadline(self) -> float:
        """When _check_alive fails for the heartbeat, unless another one comes before."""
        if not self.heartbeat_ms:
            return math.inf
        at = self.link.heartbeat_at
        return (self._connected_at if at is None else at) + self.heartbeat_timeout_s

    def _snapshot_key(self) -> tuple:
        """(_rx_lock held) What a snapshot is made of, read before it (so a change meanwhile
        makes the next key differ): the statusword and its number (an equal value is not the
        same statusword: the end of a move is the standstill before it again), the standing
        position, the cached objects, EMCY, homing and the controlword; the position's
        reception time only while moving (measured_at_s)."""
        values = self._values()
        sw, _, number = self._statusword_seen
        return (sw, number, self._standing, values.get(vm.MODES_OF_OPERATION_DISPLAY),
                values.get(vm.RSTSFLG), values.get(vm.POSITION_ACTUAL_VALUE),
                values.get(vm.VELOCITY_ACTUAL_VALUE), values.get(vm.ERROR_REGISTER),
                self.link.emcy_count, self.link.emcy, self._homing, self._cw,
                self._position_rx if sw & vm.SW_BIT_MOTOR_MOVING else None)

    def _position_measured_at_s(self, position: int, moving: bool) -> float | None:
        """When the cached position was true. A moving axis' position TxPDO goes out at most
        once per inhibit time (tpdo_inhibit_ms, [0x1800+(No.PDO-1):03] "Inibisce la trasmissione
        dei PDO per il tempo impostato"), and later still when the bus or this process is slow:
        while the axis moves, its time is the last frame's reception, however long ago. A
        standing axis sends a change at once: its position is current, None (the poll's time).
        A frame that came between the caller's read of `position` and this is not it: None."""
        rx = self._position_rx
        if not moving or rx is None or rx[1] != position:
            return None
        return rx[0]
