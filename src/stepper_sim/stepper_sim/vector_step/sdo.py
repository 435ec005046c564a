"""Vector Step simulator, SDO server checks: a part of VectorStepNode.

canopen.LocalNode serves the SDO protocol; this adds what it leaves out: value ranges from the EDS,
sub-index existence, the manual's abort codes (0x1005/0x1014 bits 29/30, 0x1016 duplicates, PDO
mapping), SDO COB-IDs (0x1200), no SDO in STOPPED. Writes to DSP-402/AEC objects go on to the
drive (`VectorStepDriveSim._on_write_device`), reads to `_on_read_device`.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
import logging
import time
from typing import Any, Callable, Protocol

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

from ..core.faults import garble_one
from .nmt import NMT_INITIALISING, NMT_STOPPED

logger = logging.getLogger(__name__)


class SdoBus(Protocol):
    """What the SDO server needs of the node's bus (a `sim.VectorStepSim`)."""

    @property
    def lock(self) -> AbstractContextManager[Any]: ...

    def after(self, fn: Callable[[], None]) -> None: ...

    def run_after(self) -> None: ...

    def wake(self) -> None: ...


class SdoNmt(Protocol):
    """... of the node's NMT slave (a `nmt.NmtSlave`), which writes of 0x1006, 0x1016 and
    0x1017 reconfigure."""

    heartbeat_due: float | None

    def load_consumers(self) -> None: ...

    def sync_watch(self, since: float | None) -> None: ...


class SdoPdo(Protocol):
    """... of the node's PDO engine (a `pdo.PdoEngine`), reloaded after a PDO parameter write."""

    def load(self) -> None: ...


class SdoNode(Protocol):
    """What the SDO server needs of its node (a `sim.VectorStepNode`): its object dictionary
    (`_obj`, `_stored`, `local`), its link to the bus (`sim`, `subscribe`, `link_cut`,
    `garble_sdo`, `nmt_state`), the other parts a write reconfigures (`nmt`, `pdo`) and the
    drive application behind the checks (`_on_read_device`, `_on_write_device`, `process`, the
    error history)."""

    id: int
    link_cut: bool
    garble_sdo: bool
    comm_error: bool
    home_error_latched: bool
    history: list[int]

    @property
    def local(self) -> canopen.LocalNode: ...

    @property
    def sim(self) -> SdoBus: ...

    @property
    def nmt(self) -> SdoNmt: ...

    @property
    def pdo(self) -> SdoPdo: ...

    @property
    def nmt_state(self) -> int: ...

    def _obj(self, index: int, sub: int) -> ODVariable: ...

    def _stored(self, index: int, sub: int = 0) -> Any: ...

    def subscribe(self, cob: int, handler: Callable) -> None: ...

    def unsubscribe(self, cob: int, handler: Callable) -> None: ...

    def unsubscribe_all(self, handler: Callable) -> None: ...

    def _on_read_device(self, index: int, subindex: int, od: ODVariable) -> Any: ...

    def _on_write_device(self, index: int, subindex: int, value: Any) -> None: ...

    def process(self) -> None: ...


class SdoServer:
    """The SDO checks of one node (`node`: see SdoNode)."""

    def __init__(self, node: SdoNode):
        self.node = node
        self.rx_cob = 0x600 + node.id
        self.tx_cob = 0x580 + node.id
        node.local.sdo.send_response = self._send_response

    def power_on(self) -> None:
        """The pre-defined SDO COB-IDs (0x600/0x580 + node-ID)."""
        self.rx_cob, self.tx_cob = 0x600 + self.node.id, 0x580 + self.node.id

    def start(self) -> None:
        """Boot-up: served on the pre-defined COB-IDs from now on."""
        local = self.node.local
        self.node.unsubscribe_all(self.on_request)
        self.power_on()
        local.sdo.rx_cobid, local.sdo.tx_cobid = self.rx_cob, self.tx_cob
        self.node.subscribe(self.rx_cob, self.on_request)

    @staticmethod
    def _check_sub(subindex: int, od: ODVariable) -> None:
        """LocalNode answers any sub-index of a VAR and invents ARRAY members: refuse them."""
        if isinstance(od.parent, (ODArray, ODRecord)):
            if subindex not in od.parent.subindices:
                raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
        elif subindex != 0:
            raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)

    def on_read(self, index: int, subindex: int, od: ODVariable) -> Any:
        """An SDO/TPDO read (LocalNode's read callback): the drive's value, None for the stored
        one."""
        self._check_sub(subindex, od)
        return self.node._on_read_device(index, subindex, od)

    def on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Validate an SDO/RPDO write (raise an abort) and apply side effects of its value."""
        node = self.node
        self._check_sub(subindex, od)
        if od.data_type == canopen.objectdictionary.VISIBLE_STRING:
            return
        value = od.decode_raw(data)
        if (od.min is not None and value < od.min) or (od.max is not None and value > od.max):
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        if index in (vm.COB_ID_SYNC, vm.COB_ID_EMCY):
            if (value ^ node._stored(index)) & (0b11 << 29):   # bits 29/30 not modifiable
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        elif index == vm.CONSUMER_HEARTBEAT_TIME:
            other = node._stored(index, 3 - subindex)
            if value & 0xFFFF and other & 0xFFFF and (value >> 16) & 0xFF == (other >> 16) & 0xFF:
                raise SdoAbortedError(vm.ABORT_PARAMETER_INCOMPATIBLE)
            node.sim.after(node.nmt.load_consumers)
        elif index == vm.PRE_DEFINED_ERROR_FIELD:
            if value != 0:
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            node.history.clear()             # "Scrivendo 0 in 0x1003:0 viene resettato lo storico"
            node.comm_error = False
            node.home_error_latched = False
        elif index == vm.PRODUCER_HEARTBEAT_TIME:
            node.nmt.heartbeat_due = time.monotonic() if value else None
        elif index == vm.COMMUNICATION_CYCLE_PERIOD:
            node.nmt.sync_watch(time.monotonic() if value else None)
            node.sim.wake()
        elif vm.RPDO_MAPPING <= index <= vm.RPDO_MAPPING + 3 or \
                vm.TPDO_MAPPING <= index <= vm.TPDO_MAPPING + 3:
            self._check_mapping(index, subindex, value)
            node.sim.after(node.pdo.load)
        elif vm.RPDO_COMMUNICATION <= index <= vm.RPDO_COMMUNICATION + 3 or \
                vm.TPDO_COMMUNICATION <= index <= vm.TPDO_COMMUNICATION + 3:
            node.sim.after(node.pdo.load)
        elif index == vm.SDO1_PARAMETER:
            node.sim.after(self._apply_cob_ids)
        else:
            node._on_write_device(index, subindex, value)

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        rx = index < vm.TPDO_MAPPING
        if sub == 0:
            total = 0
            for k in range(1, value + 1):
                entry = self.node._stored(index, k)
                self._check_entry(entry, rx)
                total += entry & 0xFF
            if total > 64:
                raise SdoAbortedError(vm.ABORT_PDO_TOO_LONG)
        elif value:
            self._check_entry(value, rx)

    def _check_entry(self, entry: int, rx: bool) -> None:
        index, sub, bits = vm.split_mapping_entry(entry)
        try:
            obj = self.node._obj(index, sub)
        except (KeyError, SdoAbortedError):
            raise SdoAbortedError(vm.ABORT_NO_OBJECT) from None
        usable = obj.writable if rx else obj.readable
        if not obj.pdo_mappable or not usable or bits != len(obj):
            raise SdoAbortedError(vm.ABORT_NOT_MAPPABLE)

    def _apply_cob_ids(self) -> None:
        node = self.node
        rx = node._stored(vm.SDO1_PARAMETER, 1) & 0x7FF
        tx = node._stored(vm.SDO1_PARAMETER, 2) & 0x7FF
        if rx != self.rx_cob:
            node.unsubscribe(self.rx_cob, self.on_request)
            self.rx_cob = rx
            node.subscribe(rx, self.on_request)
        self.tx_cob = node.local.sdo.tx_cobid = tx
        node.local.sdo.rx_cobid = rx

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        node = self.node
        with node.sim.lock:
            if node.link_cut or node.nmt_state in (NMT_INITIALISING, NMT_STOPPED):
                return                       # CiA 301: no SDO in STOPPED
            node.local.sdo.on_request(can_id, data, timestamp)
            node.sim.run_after()
            node.process()
            node.sim.wake()                  # timers may have changed

    def _send_response(self, response: bytes) -> None:
        """canopen's SdoServer.send_response, with the corrupt_reply fault."""
        if self.node.garble_sdo:
            response = garble_one(bytes(response))
        sdo = self.node.local.sdo
        sdo.network.send_message(sdo.tx_cobid, response)
