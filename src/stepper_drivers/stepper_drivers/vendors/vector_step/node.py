"""The Vector Step as a CANopen node: its boot, its liveness and its objects by SDO.

`CanopenNode` is a base of `drive.VectorStepDrive`, split from it for size: the two work on one
record (the drive's link, bus and node-ID), and only VectorStepDrive is made. Every boot
(connect) of a node (`_boot`): SDO ping, identity (0x1000, 0x1018 and the AEC registers the
driver needs: IdentityError otherwise), NMT reset communication with the boot-up latch,
heartbeat producer 0x1017, the drive-side watchdogs (0x1006 SYNC timeout, 0x1016 consumer of
this node's heartbeat), the PDO set and the values seeded by SDO (pdo.py), NMT start and a
heartbeat that shows OPERATIONAL. After that the heartbeat consumer and the boot-up latch turn
a silent or rebooted node into a LinkError (`_check_alive`; the node layer reconnects), and
`close` disarms the watchdogs. The SDO helpers of the profile objects (`_write_once`,
`_checked`) and the raw register access (`read_register`, `write_register`) are here too.

Not here: the TxPDO image (pdo.py), the CiA 402 state machine and its modes (drive.py,
modes.py). No rclpy.
"""

from __future__ import annotations

import logging
import time

from ...contract.drive import (
    DriveError,
    HomingState,
    IdentityError,
    LinkError,
    Operation,
    register_type,
)
from ...protocol.canopen_link import SdoAbortError, pack, unpack
from . import regmap as vm

# the vendor's one logger (the package's name, as before the package was split into modules)
logger = logging.getLogger(__package__)

PING_TIMEOUT_S = 0.2
RESCUE_BOOT_WAIT_S = 0.5       # boot-up wait after a reset sent to a node that gave no SDO answer
OBJECTS = {(o.index, o.sub): o for o in vm.DRIVER_OBJECTS}
# AEC registers the driver relies on; a firmware without one is not the drive this driver knows.
REQUIRED_REGISTERS = (vm.RSTPRES, vm.RCMDWR, vm.RSTSFLG, vm.RSTSFLG1, vm.RWARNING, vm.RALARM32)


def parse_address(address: str) -> tuple[int, int]:
    """'0x6041:0', '6041:00', '0x20C2' -> (index, sub); hex as CANopen writes them.

    Without a sub-index: 1 for an AEC register (0x2000-0x5FFF: sub 0 is the number of axes),
    0 otherwise.
    """
    text = address.strip().lower()
    try:
        if ':' in text:
            index_text, sub_text = text.split(':', 1)
            index, sub = int(index_text, 16), int(sub_text, 16)
        else:
            index = int(text, 16)
            sub = vm.AEC_SUB if 0x2000 <= index <= 0x5FFF else 0
    except ValueError:
        raise DriveError(f'address {address!r}: expected "index:subindex" in hex, e.g. '
                         '"0x6041:0" or "0x20C2:1"') from None
    if not (0 <= index <= 0xFFFF and 0 <= sub <= 0xFF):
        raise DriveError(f'address {address!r}: index 0..0xFFFF, sub-index 0..0xFF')
    return index, sub


class CanopenNode:
    """Boot, liveness, close and SDO access of one Vector Step (see the module).

    Uses the drive's `link` (RemoteDrive), `can` (CanBus), `node_id` and the boot, heartbeat
    and watchdog parameters VectorStepDrive.__init__ reads; `_boot` calls the image's
    `_configure_pdos` and `_seed` (pdo.py).
    """

    def _boot(self) -> Operation[dict[str, str]]:
        """From the first SDO to the heartbeat that shows OPERATIONAL (see the module), on a
        link just attached; the identity."""
        try:
            yield from self._ping()
            rebooted = False
        except LinkError:
            # A node in NMT STOPPED does not answer SDO (CiA 301), an NMT reset reaches it.
            ok = yield from self.link.reset_and_wait_bootup(
                'RESET COMMUNICATION', min(self.boot_timeout_s, RESCUE_BOOT_WAIT_S))
            if not ok:
                raise
            rebooted = True
        identity = yield from self._identity()   # before any write: is it the drive we know?
        # A defined start: communication objects back to the manual's defaults, then boot-up.
        if not rebooted:
            ok = yield from self.link.reset_and_wait_bootup('RESET COMMUNICATION',
                                                            self.boot_timeout_s)
            if not ok:
                yield from self._ping()   # CiA 301 wants a boot-up here; go on if it answers
                logger.warning('%sno boot-up frame within %g s after NMT reset communication; '
                               'the node answers SDO, continuing', self._prefix(),
                               self.boot_timeout_s)
        # Error control and the drive-side watchdogs, lost at every boot (DS-301 objects are
        # not saved [GESTIONE MEMORIA NON VOLATILE]): a missing SYNC for 0x1006 us is alarm
        # Ralarm32 bit 18 and its reaction (Ralarmreact 0x471E); a missing heartbeat of ours
        # (0x1016) only lights the LED [STATO DEL LED FLD].
        for index, sub, value in (
                (vm.PRODUCER_HEARTBEAT_TIME, 0, self.heartbeat_ms),
                (vm.COMMUNICATION_CYCLE_PERIOD, 0, round(self.sync_timeout_s * 1e6)),
                (vm.CONSUMER_HEARTBEAT_TIME, 1, self.consumer_heartbeat)):
            yield 0.0
            self.link.write(index, sub, value)
        yield from self._configure_pdos()
        yield from self._seed()
        self._bootups_at_connect = self.link.bootups
        self._connected_at = time.monotonic()
        self.link.nmt('OPERATIONAL')
        if self.heartbeat_ms:
            ok = yield from self.link.wait_heartbeat_state(
                0x05, self._connected_at, self.heartbeat_timeout_s + self.heartbeat_ms / 1000.0)
            if not ok:
                raise LinkError(f'{self._prefix()}no heartbeat showing OPERATIONAL after NMT '
                                f'start (producer {self.heartbeat_ms} ms)')
        return identity

    def _ping(self) -> Operation[None]:
        """SDO read of 0x1000 with retries: a missing node fails fast, before any NMT."""
        last: LinkError | None = None
        sdo = self.link.node.sdo
        timeout, sdo.RESPONSE_TIMEOUT = sdo.RESPONSE_TIMEOUT, min(PING_TIMEOUT_S,
                                                                  self.can.timeout_s)
        try:
            for attempt in range(max(self.boot_retries, 1)):
                if attempt:
                    yield 0.0
                try:
                    self.link.read(vm.DEVICE_TYPE)
                    return
                except LinkError as exc:
                    last = exc
        finally:
            sdo.RESPONSE_TIMEOUT = timeout
        raise LinkError(f'{self._prefix()}no answer on {self.can.description} after '
                        f'{self.boot_retries} tries ({last})')

    def _identity(self) -> Operation[dict[str, str]]:
        """Identity [DEVICE TYPE], [IDENTITY OBJECT]; IdentityError when the node is not a
        Vector Step or lacks an AEC register the driver needs."""
        device_type = int(self.link.read(vm.DEVICE_TYPE))
        if device_type & 0xFFFF != vm.DEVICE_PROFILE_DS402:
            raise IdentityError(f'{self._prefix()}0x1000 device type reads 0x{device_type:08X}: '
                                f'not a DSP-402 drive (a Vector Step reads '
                                f'0x{vm.DEVICE_TYPE_VALUE:08X})')
        yield 0.0
        vendor = int(self.link.read(vm.IDENTITY_OBJECT, 1))
        if vendor != vm.VENDOR_ID_AEC:
            raise IdentityError(f'{self._prefix()}0x1018:01 vendor-ID reads 0x{vendor:08X}, '
                                f'not AEC (0x{vm.VENDOR_ID_AEC:08X}): not a Vector Step')
        yield 0.0
        product = int(self.link.read(vm.IDENTITY_OBJECT, 2))
        if product not in vm.PRODUCT_CODES:
            known = ', '.join(f'0x{c:08X} ({n})' for c, n in vm.PRODUCT_CODES.items())
            raise IdentityError(f'{self._prefix()}0x1018:02 product code reads 0x{product:08X}, '
                                f'not a Vector Step of the manual ({known})')
        texts: dict[str, str] = {}
        for key, index, sub in (('device_name', vm.MANUFACTURER_DEVICE_NAME, 0),
                                ('software', vm.MANUFACTURER_SOFTWARE_VERSION, 0),
                                ('revision', vm.IDENTITY_OBJECT, 3),
                                ('serial', vm.IDENTITY_OBJECT, 4)):
            yield 0.0
            value = self.link.read(index, sub)
            texts[key] = f'0x{value:08X}' if key == 'revision' else str(value).strip('\0 ')
        registers: dict[int, int] = {}
        for index in REQUIRED_REGISTERS:
            yield 0.0
            registers[index] = self._probe(index)
        return {
            'node_id': str(self.node_id), 'device_name': texts['device_name'],
            'software': texts['software'], 'vendor_id': f'0x{vendor:08X}',
            'product_code': f'0x{product:08X} ({vm.PRODUCT_CODES[product]})',
            'revision': texts['revision'], 'serial': texts['serial'],
            'Rstpres': str(registers[vm.RSTPRES]), 'heartbeat_ms': str(self.heartbeat_ms),
            'sync_timeout_s': f'{self.sync_timeout_s:g}',
        }

    def _probe(self, index: int) -> int:
        """Read an AEC register (sub 1) that must exist: -1 for a write-only one that does."""
        obj = OBJECTS[(index, vm.AEC_SUB)]
        try:
            return int(self.link.read(index, vm.AEC_SUB, expected_aborts=(
                vm.ABORT_NOT_READABLE, vm.ABORT_NO_OBJECT, vm.ABORT_NO_SUBINDEX)))
        except SdoAbortError as exc:
            if exc.code == vm.ABORT_NOT_READABLE:         # write only (Rcmdwr): it exists
                return -1
            if exc.code in (vm.ABORT_NO_OBJECT, vm.ABORT_NO_SUBINDEX):
                raise IdentityError(f'{self._prefix()}{obj} is missing ({exc}): not the Vector '
                                    'Step firmware this driver knows (it needs that register)'
                                    ) from None
            raise

    # ------------------------------------------------------------------ liveness and end
    def close(self) -> None:
        """Orderly end (the node shuts down): disarm the drive-side watchdogs, so that a drive
        left standing does not fault when the SYNC stops with the bus. Nothing is written to a
        drive that is not answering (it then stops by itself, which is the point)."""
        self._homing = HomingState.IDLE
        if not self._configured or not self.link.attached:
            return                           # never armed, or not ours (IdentityError)
        try:
            self._check_alive()
            for index, sub in ((vm.COMMUNICATION_CYCLE_PERIOD, 0),
                               (vm.CONSUMER_HEARTBEAT_TIME, 1)):
                self.link.write(index, sub, 0)
        except DriveError as exc:
            logger.info('%swatchdogs left armed at close: %s', self._prefix(), exc)
        self._configured = False

    def _check_alive(self) -> None:
        if not self.link.attached:
            raise LinkError(f'{self._prefix()}not connected')
        self.can.check()
        if self.link.bootups > self._bootups_at_connect:
            raise LinkError(f'{self._prefix()}boot-up seen: the drive restarted; reconnecting '
                            'to configure it again')
        if not self.heartbeat_ms:
            return
        age = self.link.heartbeat_age_s()
        if age is None:
            age = time.monotonic() - self._connected_at
        if age > self.heartbeat_timeout_s:
            raise LinkError(f'{self._prefix()}heartbeat lost: nothing for {age:.2f} s (producer '
                            f'{self.heartbeat_ms} ms, heartbeat_timeout_s '
                            f'{self.heartbeat_timeout_s:g})')
        nmt = self.link.heartbeat_state
        if nmt is not None and nmt != 0x05:
            raise LinkError(f'{self._prefix()}heartbeat reports NMT state 0x{nmt:02X}, not '
                            'OPERATIONAL: reconnecting')

    # ------------------------------------------------------------------ SDO access
    def _write_once(self, *writes: tuple[int, int, int]) -> Operation[None]:
        """SDO writes of profile objects, each skipped when this boot already wrote the value;
        one per step."""
        for index, sub, value in writes:
            if self._written.get((index, sub)) != value:
                self.link.write(index, sub, value)
                self._written[(index, sub)] = value
                yield 0.0

    def _checked(self, index: int, sub: int, value: int, what: str) -> int:
        """`value` if the object can hold it (its type and the EDS limits), else DriveError
        naming the object: checked before anything of a command is sent."""
        obj = OBJECTS[(index, sub)]
        rtype = register_type(obj.data_type)
        low, high = (-(1 << (rtype.bits - 1)), (1 << (rtype.bits - 1)) - 1) if rtype.signed \
            else (0, (1 << rtype.bits) - 1)
        eds_low, eds_high = self.link.limits(index, sub)
        low = low if eds_low is None else max(low, eds_low)
        high = high if eds_high is None else min(high, eds_high)
        if not low <= value <= high:
            raise DriveError(f'{what}: {value} is outside {obj} ({low}..{high})')
        return value

    def read_register(self, address: str, data_type: str) -> int | str:
        index, sub = parse_address(address)
        data = self.link.upload(index, sub)
        if data_type.lower() == 'string':
            return data.split(b'\0', 1)[0].decode('latin-1')
        rtype = register_type(data_type)
        if len(data) != rtype.bits // 8:
            raise DriveError(f'0x{index:04X}:{sub:02X} answered {len(data)} byte(s); '
                             f'{rtype.name} is {rtype.bits // 8}')
        return unpack(rtype.name, data)

    def write_register(self, address: str, data_type: str, value: int | str) -> None:
        index, sub = parse_address(address)
        if data_type.lower() == 'string':
            data = str(value).encode('latin-1')
        else:
            rtype = register_type(data_type)
            data = pack(rtype.name, rtype.check(int(value)))
        self.link.download(index, sub, data)
        self._written.pop((index, sub), None)
        self._standing = None      # a register may set the position: read again at the next poll
