"""The EEPROM of a simulated AEC Vector Step: a mixin of `vector_step.device.VectorStepDriveSim`.

Rloadsav 0x20C2: save (busy for SAVE_TIME_S, then Reepsts and, on an injected NVRAM fault, EMCY
0xFF01), load and reset of the registers kept, the restart sequence 142-143; the EEPROM file in
`storage_dir`. The object dictionary it works on is VectorStepDriveSim's; not here: the
power-on state that copies the EEPROM into it (device.py).
"""

from __future__ import annotations

import functools
import json
import logging
import pathlib
import struct
import time

from canopen.sdo.exceptions import SdoAbortedError
from stepper_drivers.vendors.vector_step import regmap as vm

logger = logging.getLogger(__name__)

SAVE_TIME_S = 0.15                   # Rloadsav 0x81 busy time (EEPROM write)

# Registers stored by Rloadsav 0x81 (the SAVE note) that this simulator keeps.
SAVED_REGISTERS = (vm.RHMAXSPC, vm.RHPOS, 0x2051, vm.RCANBAUD, vm.RCANADDR, vm.RSTRTMODE,
                   vm.RSTPRES, vm.RSTRMODEOFOPERATION, vm.RALARMREACT, vm.RALMBUFFRES, 0x4801)


class VectorStepStorage:
    """The EEPROM of one Vector Step (state: VectorStepDriveSim)."""

    def _write_rloadsav(self, index: int, sub: int, value: int) -> None:
        """A write of Rloadsav: refused while a save runs, else done once it is stored."""
        if self.loadsav_busy:
            raise SdoAbortedError(vm.ABORT_DEVICE_STATE)
        self.sim.after(functools.partial(self._rloadsav, value))

    def _rloadsav(self, code: int) -> None:
        now = time.monotonic()
        if code == 0:
            return
        if code == vm.RLOADSAV_RESTART[1] and self.loadsav_last == vm.RLOADSAV_RESTART[0]:
            logger.info('%s: Rloadsav 142-143: restart', self.name)
            self._power_on_state()
            self.nmt.reset_communication()
            self.nmt.boot(self.sim.reboot_delay_s)
            return
        self.loadsav_last = code
        if code == vm.RLOADSAV_SAVE_REGISTERS:
            self.loadsav_busy = (code, now + SAVE_TIME_S)
            self.reepsts = vm.REEPSTS_BUSY
            self.sim.wake()
        elif code == vm.RLOADSAV_LOAD_REGISTERS:
            for key, value in self.eeprom.items():
                self._store(int(key, 16), vm.AEC_SUB, value)
            self.reepsts = 0
        elif code == vm.RLOADSAV_RESET_REGISTERS:
            for index in SAVED_REGISTERS:
                self.local.data_store.pop(index, None)
            self.reepsts = 0
        elif 0x01 <= code <= 0x0C or 0x82 <= code <= 0x9A:
            logger.info('%s: Rloadsav %d accepted (not simulated)', self.name, code)
            self.reepsts = 0
        else:
            self.reepsts = vm.REEPSTS_INVALID_COMMAND

    def _finish_save(self) -> None:
        self.loadsav_busy = None
        if self.nvram_fault:
            self.reepsts = 1 << 3                # "Errore in scrittura registri"
            self.nmt.emcy(vm.EMCY_NVRAM, struct.pack('<H', self.reepsts))
            return
        self.eeprom = {f'0x{index:04X}': self._stored(index, vm.AEC_SUB)
                       for index in SAVED_REGISTERS}
        path = self._eeprom_path()
        if path is not None:
            path.write_text(json.dumps({'node_id': self.id, 'registers': self.eeprom},
                                       indent=1))
        self.reepsts = 0
        logger.info('%s: registers saved to EEPROM%s', self.name,
                    f' ({path})' if path else '')

    def _eeprom_path(self) -> pathlib.Path | None:
        if not self.sim.storage_dir:
            return None
        return pathlib.Path(self.sim.storage_dir) / f'vector_step_node{self.id}.json'

    def _load_eeprom(self) -> None:
        path = self._eeprom_path()
        self.eeprom = {f'0x{vm.RSTPRES:04X}': self.cfg.step_resolution}
        if path is not None and path.exists():
            self.eeprom.update(json.loads(path.read_text())['registers'])
