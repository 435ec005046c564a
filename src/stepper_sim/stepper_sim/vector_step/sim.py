"""Simulated AEC Vector Step drives on a real CAN stack: canopen.LocalNode + what it lacks.

One `VectorStepSim` is one CAN bus (python-can; the loopback socketcand broker in tests) with one
or more `VectorStepNode`s. Each node is a `canopen.LocalNode` built from config/vector_step.eds
(the same file the driver loads), plus the parts LocalNode does not have (transports.md A5.3):
  - NMT slave: boot-up after power-on and after NMT reset node/communication (with a reboot
    delay and 10 ms between boot-up and the first heartbeat), heartbeat producer (0x1017),
    node guarding (a 0-byte frame on 0x700+ID counts as the RTR socketcand cannot carry), life
    guarding and consumer heartbeat (0x1016) with EMCY 0x8130 (and no other reaction: the
    manual ties none to them but the LED); SDO refused in STOPPED,
  - the SYNC watchdog: with 0x1006 (communication cycle period, us) not 0, no SYNC for that long
    (counted from the write of 0x1006 or the last SYNC) is the drive alarm "Mancanza Sync"
    (Ralarm32 bit 18, Rcansts "Sync error") with the alarm reaction of Ralarmreact 0x471E; the
    cause is gone with the next SYNC (or 0x1006 = 0, an NMT reset communication),
  - a PDO engine: the master's (re)mapping honoured after every SDO write, TxPDOs on change,
    on their event timer (re-armed at every event), spaced by the inhibit time, on SYNC (types
    0..240) or on request (252/253), RxPDOs into the object dictionary, applied at once (254/255)
    or at the next SYNC (0..240), EMCY 0x8210/0x8220 on a length error,
  - SDO checks LocalNode leaves out: value ranges from the EDS, sub-index existence, the
    manual's abort codes (0x1005/0x1014 bits 29/30, 0x1016 duplicates, PDO mapping),
  - the application: the simulators' shared CiA 402 (cia402.slave, not the driver's), profile
    position (absolute/relative, change set immediately, one buffered set-point), interpolated
    position (7: two-position buffer 0x60C1, one linear segment per SYNC over the period of
    0x60C2, EMCY FF03/FF04/FF05), AEC JOG velocity mode (-1), homing with the manual's
    methods on a SimAxis (BLS/FLS limit switches, TOP = encoder index), 0x607C as the position
    forced after homing, Rcmdwr STOP/ABORT, drive alarms with EMCY 0x5400 and the reaction of
    Ralarmreact, the error register 0x1001, history 0x1003 (2 entries) and 0x603F, fault reset
    as the manual's procedure ([SEGNALAZIONE DI ERRORE]), save/load through Rloadsav 0x20C2.
The simulator ignores S-curve profiles (0x6086): moves are trapezoidal. `main()` wraps it in
the common ROS simulator node (sim_node.run_sim), on the EDS installed with stepper_drivers
(`installed_eds()`). Nothing here imports the driver's state logic.

Modules, along CANopen's own seams: nmt (NmtSlave: NMT, error control, EMCY, SYNC watchdog),
sdo (SdoServer: SDO server checks), pdo (PdoEngine: PDOs), device (VectorStepDriveSim: the AEC
drive on the shared device-side cia402.slave, with its mixins modes, homing, interpolation and
storage). Here VectorStepNode is the drive (its base class) holding the three CANopen parts as
objects (`node.nmt`, `node.sdo`, `node.pdo`, each given the node and needing of it only what its
module's Protocol names: NmtNode, SdoNode, PdoNode), with the link to the bus, the timers and
fault injection; VectorStepSim runs the bus, and `main()` the ROS executable.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import sys
import threading
import time
from typing import Any, Callable, Sequence

import can
import canopen
from stepper_drivers.vendors.vector_step import regmap as vm

from ..core.axis import HOME, LIMIT_NEG, LIMIT_POS, SimAxis
from .device import FRA, OE, QSA, RTSO, SO, SOD, VectorStepDriveSim
from .nmt import NMT_INITIALISING, SYNC_CONFIRM_S, NmtSlave
from .pdo import PdoEngine
from .sdo import SdoServer

__all__ = ['NodeConfig', 'SYNC_CONFIRM_S', 'VectorStepNode', 'VectorStepSim', 'build', 'main']

logger = logging.getLogger(__name__)
logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
logging.getLogger('canopen').setLevel(logging.WARNING)    # one line per SDO otherwise


@dataclasses.dataclass
class NodeConfig:
    """One simulated drive; positions are raw (physical) steps."""

    name: str
    node_id: int
    full_steps_per_rev: int = 200
    step_resolution: int = 16            # Rstpres power-on value (micro-steps per full step)
    limit_neg_steps: float | None = None
    limit_pos_steps: float | None = None
    home_switch_steps: float | None = None
    index_phase_steps: float = 0.0
    position_steps: float = 0.0
    product_code: int = 0x138E           # another value plays a device that is no Vector Step
    vendor_id: int = vm.VENDOR_ID_AEC
    device_name: str = 'SMD50.06LIC'
    serial_number: int = 0
    power_stage_blocked: bool = False
    homing_error_faults: bool = False
    strict_fault_reset: bool = True
    # indexes answered "object does not exist" (another firmware), e.g. Ralarm32 0x222F; not
    # those the simulation itself keeps (Rstpres 0x210E, the DS-301 and DSP-402 objects)
    missing_objects: tuple[int, ...] = ()

    def __post_init__(self):
        if not 1 <= self.node_id <= 127:
            raise ValueError(f'drives.{self.name}.node_id: {self.node_id} is not a node-ID '
                             '(allowed: 1..127)')
        kept = [hex(i) for i in self.missing_objects
                if i == vm.RSTPRES or not 0x2000 <= i <= 0x5FFF]
        if kept:
            raise ValueError(f'drives.{self.name}.missing_objects: {", ".join(kept)} cannot be '
                             'missing (the simulation uses them)')
        for name in ('product_code', 'vendor_id'):
            if not 0 <= getattr(self, name) <= 0xFFFFFFFF:
                raise ValueError(f'drives.{self.name}.{name}: {getattr(self, name)} is not an '
                                 'UNSIGNED32 (0x1018)')


class VectorStepNode(VectorStepDriveSim):
    """One simulated Vector Step on the bus: the AEC drive application (the base class) with
    its CANopen parts `nmt`, `sdo` and `pdo` (as canopen's LocalNode holds its own), the node's
    link to the bus (subscriptions, `send`, `link_cut`) and its fault injection."""

    def __init__(self, sim: 'VectorStepSim', cfg: NodeConfig, eds: str):
        self.sim = sim
        self.cfg = cfg
        self.id = cfg.node_id
        self.name = cfg.name
        self.od = canopen.import_od(eds, self.id)
        for index in cfg.missing_objects:         # another firmware: SDO abort 0x06020000
            del self.od[index]
        self.local = canopen.LocalNode(self.id, self.od)
        self.garble_sdo = False          # corrupt_reply: one character of each SDO answer
        self.nmt = NmtSlave(self)
        self.sdo = SdoServer(self)
        self.pdo = PdoEngine(self)
        # LocalNode's NmtSlave runs the heartbeat as a python-can periodic task and never boots:
        # self.nmt does NMT instead.
        self.local._write_callbacks.remove(self.local.nmt.on_write)
        self.local.add_read_callback(self.sdo.on_read)
        self.local.add_write_callback(self.sdo.on_write)
        self.axis = SimAxis(limit_neg_steps=cfg.limit_neg_steps,
                            limit_pos_steps=cfg.limit_pos_steps,
                            home_switch_steps=cfg.home_switch_steps,
                            steps_per_rev=cfg.full_steps_per_rev * cfg.step_resolution,
                            index_phase_steps=cfg.index_phase_steps,
                            position_steps=cfg.position_steps)
        self.axis.add_listener(self._on_axis_event)
        self.eeprom: dict[str, int] = {}
        self.link_cut = False
        self.nvram_fault = False
        self.power_stage_blocked = cfg.power_stage_blocked
        self.alarm_causes = 0            # Ralarm32 bits whose cause is present
        self._subscriptions: list[tuple[int, Callable]] = []
        self._load_eeprom()
        self._power_on_state()

    @property
    def nmt_state(self) -> int:
        return self.nmt.state

    @property
    def sync_at(self) -> float | None:
        """The last SYNC (or 0x1006 write) the SYNC watchdog counts from."""
        return self.nmt.sync_at

    # The link to the bus ----------------------------------------------------------------------
    def attach(self) -> None:
        network = self.sim.network
        self.local.network = network
        self.local.sdo.network = network
        self.subscribe(0x000, self.nmt.on_nmt)
        self.subscribe(0x700 + self.id, self.nmt.on_guard)

    def detach(self) -> None:
        for cob, handler in self._subscriptions:
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass
        self._subscriptions.clear()

    def subscribe(self, cob: int, handler: Callable) -> None:
        self.sim.network.subscribe(cob, handler)
        self._subscriptions.append((cob, handler))

    def unsubscribe(self, cob: int, handler: Callable) -> None:
        if (cob, handler) in self._subscriptions:
            self._subscriptions.remove((cob, handler))
            try:
                self.sim.network.unsubscribe(cob, handler)
            except (KeyError, ValueError):
                pass

    def unsubscribe_all(self, handler: Callable) -> None:
        """`handler` off every COB-ID it was subscribed to."""
        for cob, subscribed in [s for s in self._subscriptions if s[1] == handler]:
            self.unsubscribe(cob, subscribed)

    def send(self, cob: int, data: bytes) -> None:
        if self.link_cut:
            return
        self.sim.send(cob, data)

    # Timers -----------------------------------------------------------------------------------
    def next_deadline(self, now: float) -> float:
        nmt = self.nmt
        times = [math.inf]
        if nmt.boot_at is not None:
            times.append(nmt.boot_at)
        if nmt.state == NMT_INITIALISING:
            return min(times)
        sync = nmt.sync_deadline()          # a cut cable loses the SYNC too
        if sync is not None:
            times.append(sync)
        if self.active:
            times.append(now + self.sim.cycle_s)
        if self.link_cut:
            return min(times)
        if self.loadsav_busy:
            times.append(self.loadsav_busy[1])
        times += nmt.deadlines()            # heartbeat, EMCY inhibit, life and consumer times
        times += self.pdo.deadlines()
        return min(times)

    @property
    def active(self) -> bool:
        return (self.axis.moving or self.homing is not None or self.cia.pending is not None
                or self.state == FRA)

    def tick(self, now: float) -> None:
        nmt = self.nmt
        if nmt.boot_at is not None and now >= nmt.boot_at:
            nmt.finish_boot(now)
        if nmt.state == NMT_INITIALISING:
            return
        nmt.check_sync(now)
        if self.link_cut:
            self.process()                  # the alarm's stop ramp runs without the bus
            return
        nmt.heartbeat(now)
        if self.loadsav_busy and now >= self.loadsav_busy[1]:
            self._finish_save()
        nmt.error_control(now)
        self.process()

    def inject(self, kind: str, code: int, value: float) -> str:
        if kind == 'drive_fault':
            bits = code or 1 << 6
            self.raise_alarm(bits)
            return (f'alarm Ralarm32 0x{bits:08X} ({vm.bit_texts(bits, vm.RALARM_BITS)}): '
                    f'EMCY 0x5400, state {self.state}')
        if kind == 'clear_fault':
            self.alarm_causes = 0
            return 'alarm causes removed (a fault reset can now succeed)'
        if kind == 'power_stage_blocked':
            self.power_stage_blocked = True
            if self.state in (RTSO, SO, OE, QSA):
                self.axis.motion.stop_immediately()
                self.homing_abort(interrupted=True)
                self.cia.force(SOD)
            return 'power stage blocked (Rstsflg1 STO): enabling stays in SWITCH ON DISABLED'
        if kind == 'power_stage_ok':
            self.power_stage_blocked = False
            return 'power stage available'
        if kind == 'warning':
            self.warnings = code
            return f'Rwarning = 0x{code:04X}'
        if kind == 'emcy':
            self.nmt.emcy(code, comm=0x8100 <= code <= 0x82FF)
            return f'EMCY 0x{code:04X} sent'
        if kind == 'nvram_fault':
            self.nvram_fault = True
            return 'Rloadsav saves fail (Reepsts bit 3, EMCY 0xFF01) until nvram_ok'
        if kind == 'nvram_ok':
            self.nvram_fault = False
            return 'EEPROM works again'
        if kind in ('cut', 'no_reply'):
            self.link_cut = True
            return 'node silent (no heartbeat, no SDO, no PDO) until link_ok'
        if kind == 'corrupt_reply':
            self.garble_sdo = True
            return ('one character of each SDO answer garbled (its index: the answer does not '
                    'fit the request) until link_ok')
        if kind == 'link_ok':
            self.link_cut = self.garble_sdo = False
            if self._stored(vm.PRODUCER_HEARTBEAT_TIME):
                self.nmt.heartbeat_due = time.monotonic()
            return 'node answers again'
        if kind == 'reboot':
            self._power_on_state()
            self.nmt.reset_communication()
            self.nmt.boot(self.sim.reboot_delay_s)
            return 'power cycle: boot-up follows'
        raise ValueError(f'unknown fault kind {kind!r}; kinds: drive_fault, clear_fault, '
                         'power_stage_blocked, power_stage_ok, warning, emcy, nvram_fault, '
                         'nvram_ok, cut, no_reply, corrupt_reply, link_ok, reboot')


# TxPDO2..4 (CiA 301 pre-defined connection set: 0x280, 0x380, 0x480 + node-ID)
LAGGED_TPDO_BASES = (0x280, 0x380, 0x480)


class VectorStepSim:
    """One CAN bus with simulated Vector Steps (a stepper_sim.core.sim_node.SimBackend)."""

    def __init__(self, nodes: Sequence[NodeConfig], *, interface: str = 'socketcand',
                 channel: str = 'can0', host: str = '127.0.0.1', port: int = 29536,
                 eds: str | None = None, reboot_delay_s: float = 0.05, cycle_s: float = 0.002,
                 storage_dir: str = '', tpdo_lag_s: float = 0.0):
        if not nodes:
            raise ValueError('parameter drives: at least one simulated drive is needed')
        ids = [n.node_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f'drives.*.node_id: {ids} has a node-ID twice (one per drive)')
        if interface == 'socketcand' and host not in ('127.0.0.1', 'localhost'):
            raise ValueError(f'can.host: {host!r}: the simulator stays on 127.0.0.1')
        self.bus_kwargs: dict[str, Any] = (
            dict(interface='socketcand', channel=channel, host=host, port=port, tcp_tune=True)
            if interface == 'socketcand' else dict(interface=interface, channel=channel))
        self.address = (f'socketcand {host}:{port} {channel}' if interface == 'socketcand'
                        else f'{interface} {channel}')
        self.reboot_delay_s = reboot_delay_s
        self.cycle_s = cycle_s
        # TxPDO2..4 leave this long after they were sampled, as on a slow or busy bus (at
        # 10-20 kbit/s a frame takes about 10 ms, and other drives' lower COB-IDs go first);
        # TxPDO1 (statusword) and every other frame at once
        self.tpdo_lag_s = tpdo_lag_s
        self.storage_dir = storage_dir
        self.lock = threading.RLock()
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1          # shutdown waits one receive timeout
        eds = eds or str(vm.eds_path())
        self.nodes = {cfg.name: VectorStepNode(self, cfg, eds) for cfg in nodes}
        self._after: list[Callable[[], None]] = []
        self._wakeup = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.sent = 0

    # SimBackend --------------------------------------------------------------------------------
    @property
    def drive_names(self) -> Sequence[str]:
        return list(self.nodes)

    def start(self) -> str:
        try:
            self.network.connect(**self.bus_kwargs)
        except (can.CanError, OSError, TimeoutError) as exc:
            raise OSError(f'{self.address}: {exc}') from None
        self.network.subscribe(0x80, self._on_sync)
        with self.lock:
            for node in self.nodes.values():
                node.attach()
                node.nmt.boot(self.reboot_delay_s)
        self._thread = threading.Thread(target=self._run, name='vector-step-sim', daemon=True)
        self._thread.start()
        ids = ', '.join(str(n.id) for n in self.nodes.values())
        return f'{self.address} (node-IDs {ids})'

    def stop(self) -> None:
        self._stopping = True
        self._wakeup.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        with self.lock:
            for node in self.nodes.values():
                node.detach()
        try:
            self.network.disconnect()
        except Exception as exc:  # noqa: BLE001 - the bus may already be gone
            logger.debug('disconnect: %s', exc)

    def true_position_steps(self, drive: str) -> float:
        with self.lock:
            node = self._node(drive)
            node.axis.update()
            return node.axis.position_steps

    def inject_fault(self, drive: str, kind: str, code: int, value: float) -> tuple[bool, str]:
        with self.lock:
            node = self._node(drive)
            try:
                message = node.inject(kind, code, value)
            except ValueError as exc:
                return False, str(exc)
            node.process()
            self.wake()
            return True, f'{drive}: {message}'

    def set_input(self, drive: str, name: str, value: bool, release: bool) -> tuple[bool, str]:
        aliases = {'bls': LIMIT_NEG, 'fls': LIMIT_POS, 'top': HOME}
        with self.lock:
            node = self._node(drive)
            name = aliases.get(name.lower(), name)
            node.axis.update()
            if release:
                node.axis.release(name)
            else:
                node.axis.set_input(name, value)
            node.process()
            self.wake()
            return True, f'{drive}: input {name} = {node._input(name)}'

    def _node(self, drive: str) -> VectorStepNode:
        try:
            return self.nodes[drive]
        except KeyError:
            raise ValueError(f'unknown drive {drive!r}; drives: {", ".join(self.nodes)}') \
                from None

    # Machinery ---------------------------------------------------------------------------------
    def send(self, cob: int, data: bytes) -> None:
        if self.tpdo_lag_s > 0 and (cob & 0x780) in LAGGED_TPDO_BASES:
            timer = threading.Timer(self.tpdo_lag_s, self._send_now, (cob, data))
            timer.daemon = True
            timer.start()
            return
        self._send_now(cob, data)

    def _send_now(self, cob: int, data: bytes) -> None:
        try:
            self.network.send_message(cob, data)
            self.sent += 1
        except (can.CanError, OSError, RuntimeError) as exc:
            logger.warning('send 0x%03X failed: %s', cob, exc)

    def after(self, fn: Callable[[], None]) -> None:
        """Run fn once the current SDO/PDO access has been stored (write callbacks run first)."""
        self._after.append(fn)

    def run_after(self) -> None:
        pending, self._after = self._after, []
        for fn in pending:
            fn()

    def wake(self) -> None:
        self._wakeup.set()

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.lock:
            now = time.monotonic()
            for node in self.nodes.values():
                if node._stored(vm.COB_ID_SYNC) & 0x7FF == can_id:
                    node.pdo.on_sync(now, timestamp)

    def _run(self) -> None:
        while not self._stopping:
            with self.lock:
                now = time.monotonic()
                deadline = min(node.next_deadline(now) for node in self.nodes.values())
            wait_s = deadline - time.monotonic()
            if wait_s > 0:
                self._wakeup.wait(min(wait_s, 0.5))
            self._wakeup.clear()
            if self._stopping:
                break
            with self.lock:
                now = time.monotonic()
                for node in self.nodes.values():
                    try:
                        node.tick(now)
                    except Exception:  # noqa: BLE001 - one broken cycle must not stop the bus
                        logger.exception('%s: cycle failed', node.name)


# ============================================================================ ROS wrapper
def build(node, eds: str | None = None) -> VectorStepSim:
    """Declare the simulator's parameters on the ROS node and build the backend (on `eds`, the
    source tree's config/vector_step.eds when None)."""
    from ..core.sim_node import declare, declare_drives
    nan = math.nan
    interface = declare(node, 'can.interface', 'socketcand', 'python-can interface')
    channel = declare(node, 'can.channel', 'can0', 'CAN channel')
    host = declare(node, 'can.host', '127.0.0.1', 'socketcand server host (loopback only)')
    port = declare(node, 'can.port', 29536, 'socketcand server port')
    reboot = declare(node, 'reboot_delay_s', 0.05, 'silence between an NMT reset and boot-up')
    cycle = declare(node, 'cycle_s', 0.002, 'application cycle while something moves [s]')
    storage = declare(node, 'storage_dir', '', 'folder for the simulated EEPROM (Rloadsav)')
    lag = declare(node, 'tpdo_lag_s', 0.0, 'TxPDO2..4 leave this long after they were sampled '
                                          '(a slow or busy bus) [s]')
    drives = declare_drives(node, ['axis1'], {
        'node_id': (0, 'CANopen node-ID (1..127)'),
        'full_steps_per_rev': (200, 'motor full steps per revolution'),
        'step_resolution': (16, 'Rstpres at power-on: micro-steps per full step'),
        'limit_neg_steps': (nan, 'BLS (backward limit switch) active below this raw position; '
                                 'NaN = none'),
        'limit_pos_steps': (nan, 'FLS (forward limit switch) active from this raw position; '
                                 'NaN = none'),
        'home_switch_steps': (nan, '0x60FD bit 2 home input from this raw position; NaN = none'),
        'position_steps': (0.0, 'raw position at power-on'),
        'product_code': (0x138E, '0x1018:02 (0x138E SMD5006, 0xBBE SMD3006; another value '
                                 'plays a device that is not a Vector Step)'),
        'vendor_id': (vm.VENDOR_ID_AEC, '0x1018:01 (0xBC AEC; another value plays another '
                                        "maker's device)"),
        'serial_number': (0, '0x1018:04 (0 = 10000 + node-ID)'),
        'power_stage_blocked': (False, 'start with the power stage blocked (STO)'),
        'homing_error_faults': (False, 'a homing error also puts the drive in FAULT'),
        'strict_fault_reset': (True, 'fault reset needs 0x1003:00 = 0 first (manual procedure)'),
    })

    def opt(value: float) -> float | None:
        return None if math.isnan(value) else float(value)

    configs = []
    for name, p in drives.items():
        configs.append(NodeConfig(
            name=name, node_id=int(p['node_id']), full_steps_per_rev=int(p['full_steps_per_rev']),
            step_resolution=int(p['step_resolution']), limit_neg_steps=opt(p['limit_neg_steps']),
            limit_pos_steps=opt(p['limit_pos_steps']),
            home_switch_steps=opt(p['home_switch_steps']),
            position_steps=float(p['position_steps']), product_code=int(p['product_code']),
            vendor_id=int(p['vendor_id']),
            serial_number=int(p['serial_number']),
            power_stage_blocked=bool(p['power_stage_blocked']),
            homing_error_faults=bool(p['homing_error_faults']),
            strict_fault_reset=bool(p['strict_fault_reset'])))
    return VectorStepSim(configs, interface=interface, channel=channel, host=host, port=int(port),
                         eds=eds, reboot_delay_s=float(reboot), cycle_s=float(cycle),
                         storage_dir=storage, tpdo_lag_s=float(lag))


def installed_eds() -> str | None:
    """config/vector_step.eds in the installed share directory of stepper_drivers, found through
    ROS's package index: an apt-style install has no source tree for vm.eds_path() to look in
    (vector_step_map imports no ROS). None when stepper_drivers is not installed."""
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        return os.path.join(get_package_share_directory('stepper_drivers'), vm.EDS_FILE)
    except PackageNotFoundError:
        return None


def main(args: list[str] | None = None) -> None:
    import faulthandler
    import signal
    faulthandler.register(signal.SIGUSR1)          # kill -USR1 <pid>: thread dump in the log
    from ..core.sim_node import run_sim
    eds = installed_eds()
    sys.exit(run_sim('vector_step_sim', lambda node: build(node, eds), args))
