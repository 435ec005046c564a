"""Vector Step simulator, SDO server checks: a mixin of VectorStepNode.

canopen.LocalNode serves the SDO protocol; this adds what it leaves out: value ranges from the EDS,
sub-index existence, the manual's abort codes (0x1005/0x1014 bits 29/30, 0x1016 duplicates, PDO
mapping), SDO COB-IDs (0x1200), no SDO in STOPPED. Writes to DSP-402/AEC objects go on to the
drive (`AecDrive._on_write_device`).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors import vector_step_map as vm

from .vector_step_nmt import NMT_INITIALISING, NMT_STOPPED

logger = logging.getLogger(__name__)


class SdoServer:
    """Object dictionary access and SDO checks of one node (state: VectorStepNode)."""

    def _obj(self, index: int, sub: int) -> ODVariable:
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if sub != 0:
                raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
            return obj
        if sub not in obj.subindices:
            raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
        return obj.subindices[sub]

    def _stored(self, index: int, sub: int = 0) -> Any:
        obj = self._obj(index, sub)
        raw = self.local.data_store.get(index, {}).get(sub)
        if raw is None:
            return obj.value if obj.value is not None else obj.default
        return obj.decode_raw(raw)

    def _store(self, index: int, sub: int, value: Any) -> None:
        obj = self._obj(index, sub)
        self.local.data_store.setdefault(index, {})[sub] = obj.encode_raw(value)

    @staticmethod
    def _check_sub(subindex: int, od: ODVariable) -> None:
        """LocalNode answers any sub-index of a VAR and invents ARRAY members: refuse them."""
        if isinstance(od.parent, (ODArray, ODRecord)):
            if subindex not in od.parent.subindices:
                raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)
        elif subindex != 0:
            raise SdoAbortedError(vm.ABORT_NO_SUBINDEX)

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Validate an SDO/RPDO write (raise an abort) and apply side effects of its value."""
        self._check_sub(subindex, od)
        if od.data_type == canopen.objectdictionary.VISIBLE_STRING:
            return
        value = od.decode_raw(data)
        if (od.min is not None and value < od.min) or (od.max is not None and value > od.max):
            raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        if index in (vm.COB_ID_SYNC, vm.COB_ID_EMCY):
            if (value ^ self._stored(index)) & (0b11 << 29):   # bits 29/30 not modifiable
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
        elif index == vm.CONSUMER_HEARTBEAT_TIME:
            other = self._stored(index, 3 - subindex)
            if value & 0xFFFF and other & 0xFFFF and (value >> 16) & 0xFF == (other >> 16) & 0xFF:
                raise SdoAbortedError(vm.ABORT_PARAMETER_INCOMPATIBLE)
            self.sim.after(self._load_consumers)
        elif index == vm.PRE_DEFINED_ERROR_FIELD:
            if value != 0:
                raise SdoAbortedError(vm.ABORT_VALUE_RANGE)
            self.history.clear()             # "Scrivendo 0 in 0x1003:0 viene resettato lo storico"
            self.comm_error = False
            self.home_error_latched = False
        elif index == vm.PRODUCER_HEARTBEAT_TIME:
            self.heartbeat_due = time.monotonic() if value else None
        elif index == vm.COMMUNICATION_CYCLE_PERIOD:
            self._sync_watch(time.monotonic() if value else None)
            self.sim.wake()
        elif vm.RPDO_MAPPING <= index <= vm.RPDO_MAPPING + 3 or \
                vm.TPDO_MAPPING <= index <= vm.TPDO_MAPPING + 3:
            self._check_mapping(index, subindex, value)
            self.sim.after(self._load_pdos)
        elif vm.RPDO_COMMUNICATION <= index <= vm.RPDO_COMMUNICATION + 3 or \
                vm.TPDO_COMMUNICATION <= index <= vm.TPDO_COMMUNICATION + 3:
            self.sim.after(self._load_pdos)
        elif index == vm.SDO1_PARAMETER:
            self.sim.after(self._apply_sdo_cob_ids)
        else:
            self._on_write_device(index, subindex, value)

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        rx = index < vm.TPDO_MAPPING
        if sub == 0:
            total = 0
            for k in range(1, value + 1):
                entry = self._stored(index, k)
                self._check_entry(entry, rx)
                total += entry & 0xFF
            if total > 64:
                raise SdoAbortedError(vm.ABORT_PDO_TOO_LONG)
        elif value:
            self._check_entry(value, rx)

    def _check_entry(self, entry: int, rx: bool) -> None:
        index, sub, bits = vm.split_mapping_entry(entry)
        try:
            obj = self._obj(index, sub)
        except (KeyError, SdoAbortedError):
            raise SdoAbortedError(vm.ABORT_NO_OBJECT) from None
        usable = obj.writable if rx else obj.readable
        if not obj.pdo_mappable or not usable or bits != len(obj):
            raise SdoAbortedError(vm.ABORT_NOT_MAPPABLE)

    def _apply_sdo_cob_ids(self) -> None:
        rx = self._stored(vm.SDO1_PARAMETER, 1) & 0x7FF
        tx = self._stored(vm.SDO1_PARAMETER, 2) & 0x7FF
        if rx != self.sdo_rx_cob:
            self._unsubscribe(self.sdo_rx_cob, self._on_sdo)
            self.sdo_rx_cob = rx
            self._subscribe(rx, self._on_sdo)
        self.sdo_tx_cob = self.local.sdo.tx_cobid = tx
        self.local.sdo.rx_cobid = rx

    def _on_sdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.sim.lock:
            if self.link_cut or self.nmt_state in (NMT_INITIALISING, NMT_STOPPED):
                return                       # CiA 301: no SDO in STOPPED
            self.local.sdo.on_request(can_id, data, timestamp)
            self.sim.run_after()
            self.process()
            self.sim.wake()                  # timers may have changed
