"""CANopen master side on python-can + canopen 2.4.1: the bus.

`CanBus` is one python-can bus (socketcand to the loopback broker in tests, `socketcan` `can0`
on hardware) with one `canopen.Network`. While it is open it produces what the drives watch:
SYNC every `sync_period_s` (the drives' 0x1006 watchdog) and a heartbeat of its own
(`master_node_id`, every `master_heartbeat_ms`; the drives' 0x1016 consumer), from a producer
the node's other threads cannot hold up (canopen_producers: a process of its own on socketcand,
the kernel on socketcan, a thread at the owners' real-time priority elsewhere) that ends with
the bus or the process; when the SYNCs went out is kept (`sync_record`): the largest gap and a
WARN as it nears the drives' 0x1006 time are in health() and counters(). Frames that do not fit
what a subscribed COB-ID carries (length, heartbeat state) are dropped, counted as link errors
and logged in one line (`CheckedNetwork`); so are the error frames the interface reports, which
canopen ignores (`error_frames`, and `bus_off` where SocketCAN's encoding tells it;
`CheckedListener`).
Every drive on the bus is a `RemoteDrive` (canopen_remote: a `canopen.BaseNode402` plus what
the library leaves to the application: boot-up latch, heartbeat consumer, EMCY record, SDO
errors mapped to the project's, PDO mapping); it, its errors and helpers are re-exported here.
No rclpy here.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from typing import Any, Callable

import can
import canopen

from ..contract.capabilities import ChangeCounting
from ..contract.drive import Bus, LinkError
from .canopen_producers import (
    PERSISTENT_ERRORS,
    Cyclic,
    ProducerProcess,
    ProducerThread,
    SyncRecord,
)
from .canopen_remote import (  # noqa: F401 - re-exported: the vendors import them from here
    COMMUNICATION_CYCLE_PERIOD,
    NMT_COMMANDS,
    NMT_STATES,
    PDO_STRUCT_CHARS,
    POLL_S,
    EmcyRecord,
    RemoteDrive,
    SdoAbortError,
    check_heartbeat,
    check_length,
    emcy_code_text,
    pack,
    unpack,
)

logger = logging.getLogger(__name__)

# python-can's socketcand client logs a warning whenever a TCP read ends mid-frame (harmless).
logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)

PROBE_TIMEOUT_S = 1.0
SYNC_COB_ID = 0x080            # 0x1005 default ("0x80 or 0x80000080")
# A gap between SYNCs of this share of the smallest 0x1006 time (and of at least this many SYNC
# periods) is a WARN in health(): the SYNC is late, the drives have not faulted yet.
SYNC_GAP_WARN_SHARE = 0.5
SYNC_GAP_WARN_PERIODS = 1.5
# python-can's own SYNC for these interfaces: the kernel's broadcast manager (no thread of ours)
KERNEL_PERIODIC_INTERFACES = ('socketcan',)
GARBAGE_LOG_PERIOD_S = 10.0    # one log line per COB-ID and period for frames that do not fit
# An error frame or a bus-off shows in /diagnostics and the drives' status alarms this long.
HEALTH_WINDOW_S = 10.0
# Error frames in SocketCAN's encoding (linux/can/error.h): the error class bits in the CAN ID,
# controller details in data[1]. python-can's socketcan and socketcand interfaces deliver them so
# (is_error_frame); other interfaces encode theirs in their own way: counted, not decoded.
SOCKETCAN_ERROR_INTERFACES = ('socketcan', 'socketcand')
CAN_ERR_CRTL = 0x004
CAN_ERR_BUSOFF = 0x040
CAN_ERR_CLASSES = {0x001: 'TX timeout', 0x002: 'lost arbitration', CAN_ERR_CRTL: 'controller',
                   0x008: 'protocol violation', 0x010: 'transceiver', 0x020: 'no ACK',
                   CAN_ERR_BUSOFF: 'BUS-OFF', 0x080: 'bus error',
                   0x100: 'controller restarted'}
CAN_ERR_CRTL_STATES = {0x01: 'RX overflow', 0x02: 'TX overflow', 0x04: 'RX warning',
                       0x08: 'TX warning', 0x10: 'RX error passive', 0x20: 'TX error passive',
                       0x40: 'error active again'}
MASTER = '(this node)'         # CanBus._node_ids value of the node's own heartbeat node-ID
# A producer refused its real-time priority: said once per process (as the bus owners do).
_refusal_lock = threading.Lock()
_refusal_told = False


class CheckedNetwork(canopen.Network):
    """A canopen.Network that checks each received frame against what its COB-ID carries.

    A frame that does not fit (a heartbeat that is not one byte with a CiA 301 state, an EMCY or
    SDO answer that is not 8 bytes, a TxPDO whose length is not its mapping's) never reaches
    canopen (whose callbacks raise KeyError/struct.error on them, logged with no count); it is
    counted in the bus' link errors and logged in one line. So is any error a callback raises.
    The dispatch is canopen's Network.notify (subscribers by COB-ID, then the node scanner)
    with the check in front, in one call: it runs for every frame in the receive thread.
    """

    def __init__(self, bus: 'CanBus'):
        super().__init__()
        self.owner = bus
        self.listeners = [CheckedListener(self)]

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        check = self.owner.frame_checks.get(can_id)
        problem = check(data) if check is not None else ''
        if not problem:
            try:
                callbacks = self.subscribers.get(can_id)
                if callbacks:
                    for callback in callbacks:
                        callback(can_id, data, timestamp)
                self.scanner.on_message_received(can_id)
                return
            except Exception as exc:  # noqa: BLE001 - a frame must not stop the receive thread
                problem = f'{type(exc).__name__}: {exc}'
        self.owner.garbage(can_id, bytes(data), problem)


class CheckedListener(can.Listener):
    """canopen's MessageListener, which drops the error frames the interface reports, with
    those handed to the bus (CanBus.error_frame): one listener, so python-can's Notifier makes
    one call per frame."""

    def __init__(self, network: CheckedNetwork):
        self.network = network

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.network.owner.error_frame(msg.arbitration_id, bytes(msg.data))
        elif not msg.is_remote_frame:
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)

    def stop(self) -> None:
        pass


def error_frame_text(can_id: int, data: bytes) -> str:
    """A SocketCAN error frame in words: its classes, the controller's state."""
    parts = [name for bit, name in CAN_ERR_CLASSES.items() if can_id & bit]
    if can_id & CAN_ERR_CRTL and len(data) > 1:
        parts += [name for bit, name in CAN_ERR_CRTL_STATES.items() if data[1] & bit]
    return ', '.join(parts) or f'error class 0x{can_id:03X}'


class CanBus(Bus, ChangeCounting):
    """One CAN bus (python-can) carrying one canopen.Network; several drives share it. It counts
    what its drives send by themselves (`changes`, ChangeCounting: the link's cache)."""

    def __init__(self, interface: str = 'socketcand', channel: str = 'can0',
                 bitrate: int = 125000, host: str = '127.0.0.1', port: int = 29536,
                 timeout_s: float = 0.5, sync_period_s: float = 0.0,
                 master_node_id: int = 127, master_heartbeat_ms: int = 0,
                 owner_thread_priority: int = 0):
        self.interface = interface
        self.channel = channel
        self.bitrate = int(bitrate)
        self.host = host
        self.port = int(port)
        self.timeout_s = float(timeout_s)
        self.sync_period_s = float(sync_period_s)         # 0: no SYNC producer
        self.master_node_id = int(master_node_id)
        self.master_heartbeat_ms = int(master_heartbeat_ms)   # 0: no heartbeat of our own
        # the SYNC and heartbeat producer's real-time priority: the bus owners' (SCHED_FIFO,
        # 1..99; 0: the normal scheduler), whichever thread opens the bus
        self.owner_thread_priority = int(owner_thread_priority)
        self.network: canopen.Network | None = None
        self.generation = 0              # +1 at every open(): drives re-attach their nodes
        # The SYNC and heartbeat producer (canopen_producers), started by open(), stopped by
        # close(): a ProducerProcess or ProducerThread, or on socketcan the kernel's cyclic
        # tasks (python-can send_periodic) by name ('sync', 'heartbeat').
        self._producer: ProducerProcess | ProducerThread | None = None
        self._kernel_tasks: dict[str, Any] = {}
        self.sync_record = SyncRecord()  # when the SYNCs went out
        # 0x1006 [s] of each drive as written (RemoteDrive.write); 0 = not watched
        self.sync_timeouts: dict[str, float] = {}
        self._send_error_logged = -GARBAGE_LOG_PERIOD_S
        self._node_ids: dict[int, str] = {}
        if self.master_heartbeat_ms:
            self._node_ids[self.master_node_id] = MASTER
        self.frame_checks: dict[int, Callable[[bytes], str]] = {}   # COB-ID -> problem or ''
        self._garbage_logged: dict[int, float] = {}
        self.extra: dict[str, int] = {'tpdo_rx': 0, 'emcy_rx': 0, 'heartbeat_rx': 0,
                                      'bootups': 0, 'garbage_rx': 0, 'error_frames': 0,
                                      'bus_off': 0}
        self._error_frame_logged = -GARBAGE_LOG_PERIOD_S
        # (monotonic time, words) of the last error frame and of the last bus-off (health())
        self._last_error_frame: tuple[float, str] | None = None
        self._last_bus_off: float | None = None
        if interface == 'socketcand':
            self.description = f'CAN socketcand {host}:{port} {channel}'
        else:
            self.description = f'CAN {interface} {channel} {bitrate // 1000} kbit/s'

    def claim(self, node_id: int, name: str) -> None:
        """Reserve a node-ID for a drive; two drives with one node-ID is a configuration error."""
        other = self._node_ids.get(node_id)
        if other == MASTER:
            raise ValueError(f'drives.{name}.node_id: {node_id} is can.master_node_id, the '
                             "node-ID of this node's own heartbeat (allowed: 1..127, one per "
                             'device)')
        if other is not None and other != name:
            raise ValueError(f'drives.{name}.node_id: {node_id} is already the node-ID of '
                             f'drive {other!r} on this bus (allowed: 1..127, one per drive)')
        self._node_ids[node_id] = name

    @property
    def drive_count(self) -> int:
        return sum(1 for name in self._node_ids.values() if name != MASTER)

    def _bus_kwargs(self) -> dict[str, Any]:
        if self.interface == 'socketcand':
            return dict(interface='socketcand', channel=self.channel, host=self.host,
                        port=self.port, tcp_tune=True)
        return dict(interface=self.interface, channel=self.channel, bitrate=self.bitrate)

    def open(self) -> None:
        if self.interface == 'socketcand':
            # python-can retries connect() in a busy loop for 10 s: find out first.
            try:
                socket.create_connection((self.host, self.port), PROBE_TIMEOUT_S).close()
            except OSError as exc:
                raise LinkError(f'{self.description}: cannot connect ({exc}); is the '
                                'socketcand server (broker) running?') from None
        network = CheckedNetwork(self)
        network.NOTIFIER_CYCLE = 0.1               # close() waits one receive timeout
        try:
            network.connect(**self._bus_kwargs())
            # The drives' watchdogs: a missing SYNC is a drive alarm (0x1006, Ralarm32 bit 18),
            # a missing heartbeat only their LED (0x1016). They stop with the bus (close) and
            # with the process.
            network.sync.cob_id = SYNC_COB_ID
            self._start_producer(network)
        except (can.CanError, OSError, ValueError, TimeoutError) as exc:
            try:
                self._stop_producer()
                network.disconnect()
            except Exception:  # noqa: BLE001 - half-open: close what there is
                pass
            raise LinkError(f'{self.description}: {type(exc).__name__}: {exc}') from None
        self.network = network
        self.generation += 1
        logger.info('opened %s%s', self.description,
                    f', SYNC every {self.sync_period_s:g} s' if self.sync_period_s else '')

    # The producer ------------------------------------------------------------------------------
    def _frames(self) -> list[Cyclic]:
        frames = []
        if self.sync_period_s:
            frames.append(Cyclic('sync', SYNC_COB_ID, b'', self.sync_period_s))
        if self.master_heartbeat_ms:
            frames.append(Cyclic('heartbeat', 0x700 + self.master_node_id, bytes([0x05]),
                                 self.master_heartbeat_ms / 1000.0))
        return frames

    def _start_producer(self, network: canopen.Network) -> None:
        """SYNC and heartbeat (open(), the opening thread): see canopen_producers for which
        producer a link gets, and why."""
        frames = self._frames()
        self.sync_record.restart()
        if not frames:
            return
        name = f'SYNC producer {self.description}'
        if self.interface == 'socketcand':
            producer = ProducerProcess(name, frames, self.host, self.port, self.channel,
                                       self.sync_record, self.owner_thread_priority,
                                       self._refused, self._send_errors)
            producer.start()
            self._producer = producer
        elif self.interface in KERNEL_PERIODIC_INTERFACES:
            # The kernel sends them (no thread of ours); the node receives its own SYNCs from
            # the kernel's loopback with the kernel's time: the record takes them from there.
            network.subscribe(SYNC_COB_ID, self._sync_seen)
            for frame in frames:
                self._kernel_tasks[frame.name] = network.bus.send_periodic(
                    can.Message(arbitration_id=frame.cob_id, data=frame.data,
                                is_extended_id=False), frame.period_s)
        else:
            producer = ProducerThread(name, frames, network.send_message, self.sync_record,
                                      self.owner_thread_priority, self._refused,
                                      self._send_errors)
            producer.start()
            self._producer = producer

    def _sync_seen(self, _can_id: int, _data: bytearray, timestamp: float) -> None:
        """(Receive thread, socketcan) a SYNC the kernel sent, at its time.time() stamp."""
        t = timestamp - (time.time() - time.monotonic())
        self.sync_record.merge(1, t, t, 0.0)

    def _refused(self, why: str) -> None:
        global _refusal_told
        with _refusal_lock:
            told, _refusal_told = _refusal_told, True
        if not told:
            logger.warning('%s: the SYNC and heartbeat producer: owner_thread_priority %d: %s: '
                           'it runs on the normal scheduler (a loaded machine may delay the '
                           'SYNC); allow it as for the bus owners (docs/vector_step.md)',
                           self.description, self.owner_thread_priority, why)

    def _send_errors(self, count: int, text: str) -> None:
        """(The producer's thread, or the node's link thread of its process) failed sends:
        link errors; one log line per GARBAGE_LOG_PERIOD_S."""
        self.errors += count
        now = time.monotonic()
        if now - self._send_error_logged >= GARBAGE_LOG_PERIOD_S:
            self._send_error_logged = now
            logger.warning('%s: link error: a cyclic frame was not sent: %s (%d failed sends so '
                           'far; the next goes on time)', self.description, text,
                           self.sync_record.errors)

    def _stop_producer(self) -> None:
        """Stop the producer and wait for it: a process or thread that outlived close() would
        send on a closed bus."""
        producer, self._producer = self._producer, None
        tasks, self._kernel_tasks = self._kernel_tasks, {}
        if producer is not None:
            producer.stop()
        for task in tasks.values():
            task.stop()

    # SYNC from the bus owner (interpolated position mode): one set point per drive, then one
    # SYNC, so a drive's two-position buffer neither runs dry (EMCY FF03) nor over.
    def own_sync(self) -> None:
        """The periodic SYNC stops (the heartbeat goes on); the owner sends each SYNC
        (send_sync). Returns once the producer has confirmed it (at most PAUSE_TIMEOUT_S)."""
        task = self._kernel_tasks.pop('sync', None)
        if task is not None:
            task.stop()
        if self._producer is not None and self.sync_period_s \
                and not self._producer.pause('sync'):
            logger.warning('%s: the SYNC producer did not confirm the pause: a periodic SYNC '
                           'may still come', self.description)

    def send_sync(self) -> None:
        if self.network is not None:
            self.sync_record.sent(time.monotonic())
            self.network.sync.transmit()
            self.transactions += 1

    def periodic_sync(self) -> None:
        """The periodic producer again (the drives' 0x1006 watchdog needs it)."""
        network = self.network
        if network is None or not self.sync_period_s:
            return
        if self._producer is not None:
            self._producer.resume('sync')
        elif self.interface in KERNEL_PERIODIC_INTERFACES and 'sync' not in self._kernel_tasks:
            self._kernel_tasks['sync'] = network.bus.send_periodic(
                can.Message(arbitration_id=SYNC_COB_ID, data=b'', is_extended_id=False),
                self.sync_period_s)

    def sync_watch(self, name: str, timeout_s: float) -> None:
        """A drive's 0x1006 time [s] (0: not watched): the SYNC gaps are judged against the
        smallest."""
        if timeout_s > 0:
            self.sync_timeouts[name] = timeout_s
        else:
            self.sync_timeouts.pop(name, None)

    @property
    def producer_pid(self) -> int | None:
        """The process id of the SYNC producer's process (socketcand), else None."""
        producer = self._producer
        return producer.pid if isinstance(producer, ProducerProcess) else None

    @property
    def producer_tid(self) -> int | None:
        """The thread id of the SYNC producer's thread (interfaces other than socketcand and
        socketcan), else None."""
        producer = self._producer
        return producer.native_id if isinstance(producer, ProducerThread) else None

    def _producer_failure(self) -> str:
        """Why the producer no longer sends, or ''."""
        producer = self._producer
        if producer is not None and producer.failure:
            return producer.failure
        record = self.sync_record
        if record.failing >= PERSISTENT_ERRORS:
            return (f'{record.failing} cyclic frames in a row not sent, last: '
                    f'{record.last_error}')
        return ''

    def close(self) -> None:
        network, self.network = self.network, None
        if network is None:
            return
        try:
            self._stop_producer()
            network.disconnect()
        except Exception as exc:  # noqa: BLE001 - a dead bus may fail to close in any way
            logger.debug('closing %s: %s', self.description, exc)

    @property
    def is_open(self) -> bool:
        return self.network is not None

    @property
    def receiving(self) -> bool:
        """Open, its receive thread has not died and its SYNC producer sends (check() would not
        raise)."""
        network = self.network
        return network is not None and (network.notifier is None
                                        or network.notifier.exception is None) \
            and not self._producer_failure()

    def check(self) -> canopen.Network:
        """The network, or LinkError when closed, its receive thread died, or its SYNC
        producer has ended or fails to send (the owner then reconnects: a new producer)."""
        network = self.network
        if network is None:
            raise LinkError(f'{self.description} is closed')
        try:
            network.check()
        except Exception as exc:  # noqa: BLE001 - whatever killed the notifier thread
            raise LinkError(f'{self.description}: receive thread stopped: {exc}') from None
        failure = self._producer_failure()
        if failure:
            raise LinkError(f'{self.description}: SYNC and heartbeat not sent: {failure}')
        return network

    def send(self, can_id: int, data: bytes) -> None:
        try:
            self.check().send_message(can_id, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self.errors += 1
            raise LinkError(f'{self.description}: send 0x{can_id:03X} failed: {exc}') from None

    def counters(self) -> dict[str, int]:
        out = {'transactions': self.transactions, 'errors': self.errors, **self.extra}
        if self.sync_period_s:
            out['sync_gap_max_ms'] = round(self._sync_gap_s() * 1000.0)
        return out

    def _sync_gap_s(self) -> float:
        """The largest gap between SYNCs within HEALTH_WINDOW_S, and the open one (none while
        closed, or on the kernel's producer: the record hears of its SYNCs late when the
        receive thread is)."""
        producer = self._producer
        if producer is not None:
            producer.refresh()
        open_slack = getattr(producer, 'slack_s', 0.0) if self.network is not None \
            and producer is not None else None
        return self.sync_record.gap_max_s(HEALTH_WINDOW_S, open_slack)

    def garbage(self, can_id: int, data: bytes, problem: str) -> None:
        """A received frame that does not fit its COB-ID (receive thread): count, log a line."""
        self.errors += 1
        self.extra['garbage_rx'] += 1
        now = time.monotonic()
        if now - self._garbage_logged.get(can_id, -GARBAGE_LOG_PERIOD_S) >= \
                GARBAGE_LOG_PERIOD_S:
            self._garbage_logged[can_id] = now
            logger.warning('%s: link error: frame 0x%03X [%d] %s dropped: %s (%d such frames '
                           'so far)', self.description, can_id, len(data), data.hex(' '),
                           problem, self.extra['garbage_rx'])

    def error_frame(self, can_id: int, data: bytes) -> None:
        """An error frame from the interface (receive thread): a link error, counted in
        error_frames (and bus_off); logged at once for bus-off, else one line per period."""
        self.errors += 1
        self.extra['error_frames'] += 1
        decoded = self.interface in SOCKETCAN_ERROR_INTERFACES
        bus_off = decoded and bool(can_id & CAN_ERR_BUSOFF)
        now = time.monotonic()
        what = error_frame_text(can_id, data) if decoded else 'an error frame'
        self._last_error_frame = (now, what)
        if bus_off:
            self.extra['bus_off'] += 1
            self._last_bus_off = now
        if bus_off or now - self._error_frame_logged >= GARBAGE_LOG_PERIOD_S:
            self._error_frame_logged = now
            logger.warning('%s: link error: the CAN interface reports %s (0x%03X [%d] %s; %d '
                           'error frames so far)', self.description, what, can_id, len(data),
                           data.hex(' '), self.extra['error_frames'])

    def health(self) -> tuple[str, str] | None:
        """An error frame within the last HEALTH_WINDOW_S: 'warn' (the controller saw errors:
        wiring, termination, a bit rate that differs); a bus-off: 'error' (the controller
        stopped sending until it recovers: no SYNC, no command reaches a drive). A gap between
        SYNCs within HEALTH_WINDOW_S (or one still open) that nears the smallest 0x1006 time of
        the drives (SYNC_GAP_WARN_SHARE of it): 'warn', naming both, before the drives fault;
        'error' once it is that long (they fault: missing SYNC); a SYNC producer that ended
        or fails to send: 'error'. The texts stay the same while they last (a status goes out
        when its alarms change), but that of an open gap, which grows; the counts are in
        counters()."""
        now = time.monotonic()
        problems: list[tuple[str, str]] = []
        bus_off, last = self._last_bus_off, self._last_error_frame
        if bus_off is not None and now - bus_off < HEALTH_WINDOW_S:
            problems.append(('error', f'CAN bus-off within {HEALTH_WINDOW_S:g} s (the '
                                      'controller sends nothing until it recovers)'))
        elif last is not None and now - last[0] < HEALTH_WINDOW_S:
            problems.append(('warn', f'CAN error frames within {HEALTH_WINDOW_S:g} s, last: '
                                     f'{last[1]}'))
        failure = self._producer_failure() if self.network is not None else ''
        if failure:
            problems.append(('error', f'SYNC and heartbeat not sent: {failure}'))
        sync = self._sync_gap_health()
        if sync is not None:
            problems.append(sync)
        if not problems:
            return None
        level = 'error' if any(p[0] == 'error' for p in problems) else 'warn'
        return level, '; '.join(p[1] for p in problems)

    def _sync_gap_health(self) -> tuple[str, str] | None:
        timeouts = [t for t in self.sync_timeouts.values() if t > 0]
        if not self.sync_period_s or not timeouts:
            return None
        timeout_s = min(timeouts)
        gap_s = self._sync_gap_s()
        warn_s = max(SYNC_GAP_WARN_SHARE * timeout_s, SYNC_GAP_WARN_PERIODS * self.sync_period_s)
        if gap_s < warn_s:
            return None
        gap_ms, timeout_ms = round(gap_s * 1000.0), round(timeout_s * 1000.0)
        if gap_s >= timeout_s:
            return 'error', (f"SYNC gap {gap_ms} ms: the drives' {timeout_ms} ms "
                             'sync_timeout_s ran out (missing SYNC)')
        return 'warn', f"SYNC gap {gap_ms} ms of the drives' {timeout_ms} ms sync_timeout_s"
