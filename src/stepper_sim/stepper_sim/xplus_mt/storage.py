"""One simulated R.T.A. X-PLUS MT, its parameter storage: a mixin of `XplusMtDriveSim`.

The signature registers (§13 "Register 1260", "Register 1261"): save the parameters (0x6173) or
the IP registers into a JSON file per unit in `storage_dir`, restore the defaults (in RAM), and
the load of that file at power-on. The register image it works on is
`xplus_mt.device.XplusMtDriveSim`'s; not here: the Modbus access that reaches it.
"""

from __future__ import annotations

import json
import logging
import os

from stepper_drivers.vendors.xplus_mt import regmap as xm

logger = logging.getLogger(__name__)


class XplusMtStorage:
    """The parameter storage of one X-PLUS MT (register image: XplusMtDriveSim)."""

    def storage_path(self) -> str | None:
        if not self.storage_dir:
            return None
        return os.path.join(self.storage_dir, f'xplus_mt_unit{self.unit_id}.json')

    def _load_storage(self) -> None:
        path = self.storage_path()
        if not path or not os.path.exists(path):
            return
        try:
            with open(path, encoding='utf-8') as f:
                data = json.load(f)
            for section in ('registers', 'ip_registers'):
                for key, value in data.get(section, {}).items():
                    reg = xm.BY_ADDRESS.get(int(key))
                    if reg is not None and reg.accepts(int(value)):
                        self._regs[reg.address] = int(value)
        except (OSError, ValueError) as exc:
            logger.warning('%s: storage %s not loaded: %s', self.name, path, exc)

    def _signature(self, address: int, value: int) -> None:
        if address == xm.RESTORE_DEFAULTS_REGISTER:
            for a in xm.STORABLE:
                self._regs[a] = xm.BY_ADDRESS[a].default   # [R] RAM now; 0x6173 makes it stay
            logger.info('%s: default parameters restored', self.name)
            return
        path = self.storage_path()
        if value == xm.SAVE_PARAMS_SIGNATURE:
            section, addresses = 'registers', xm.STORABLE
        else:
            section, addresses = 'ip_registers', xm.IP_REGISTERS
        if not path:
            logger.info('%s: save (0x%04X) accepted; no storage_dir, kept in RAM only',
                        self.name, value)
            return
        data: dict = {}
        if os.path.exists(path):
            try:
                with open(path, encoding='utf-8') as f:
                    data = json.load(f)
            except (OSError, ValueError):
                data = {}
        data.update({'device': 'R.T.A. X-PLUS MT (simulated)', 'unit_id': self.unit_id})
        data[section] = {str(a): self._regs[a] for a in addresses}
        data.setdefault('names', {}).update({str(a): xm.BY_ADDRESS[a].name for a in addresses})
        os.makedirs(self.storage_dir, exist_ok=True)
        tmp = f'{path}.tmp'
        with open(tmp, 'w', encoding='utf-8') as f:
            json.dump(data, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
        logger.info('%s: %s stored in %s', self.name, section, path)
