"""What a CANopen master sends on a clock of its own for the drives to watch: SYNC (COB-ID 0x080;
the drives' communication cycle period 0x1006 is its watchdog, [COMMUNICATION CYCLE PERIOD]) and
its own heartbeat (0x700 + node-ID; their consumer heartbeat 0x1016).

Not a thread of the node: every thread of a Python process needs the process' GIL, whatever its
scheduling priority, and a node holds the GIL in calls that block. rclpy calls rcl_publish with
the GIL held; on a loaded two-core machine a DriveStatus publish of the bus owner waited 120-330
ms inside Fast DDS (on a lock of a DDS thread at the normal priority), while python-can's SYNC
thread, already at the owner's SCHED_FIFO priority, waited for the GIL as long: the SYNC left
late by as much. A drive faults when it is late by its 0x1006 time (0.5 s by default).

So the producer has a GIL of its own where the link allows a second handle:
  - socketcand (`can.interface` socketcand: the loopback broker of the tests and the demo, or a
    socketcand daemon on a CAN host): `ProducerProcess`, this file run as a script. One thread
    in a process of its own, standard library only, at the bus owners' real-time priority
    (owner_thread_priority; refused: a warning, and the normal scheduler), on its own
    connection in socketcand's BCM mode (`< send ... >`, and no frame comes back to it),
    sending on an absolute schedule. It ends with the node (EOF on its stdin: a killed node
    takes its SYNC along) and stops sending while the node gives no sign of life for
    `LEASE_S` (a node that hangs, however, sends no SYNC: the drives stop on their watchdog);
  - socketcan: the Linux kernel's broadcast manager sends them (python-can's send_periodic on a
    socketcan bus: no thread of ours, and CanBus reads the SYNCs' times from its own receive);
  - any other interface (pcan, kvaser, slcan, python-can's in-process virtual bus: one handle
    per channel): `ProducerThread`, the same schedule in a thread of the node at the owners'
    real-time priority. It cannot run while another thread holds the GIL.
A send error never stops a producer: it is counted (the link's errors), reported, and the next
frame is tried on time; errors that persist (`PERSISTENT_ERRORS` frames in a row) are a link
error the bus owner sees (CanBus.check raises LinkError, the owner reconnects the bus).

`SyncRecord` keeps when the SYNCs went out, for the link's /diagnostics (CanBus.health,
CanBus.counters): the largest gap between two SYNCs within a window, and the gap still open.

Threads: a ProducerProcess has, in the node, its `link` thread (keep-alives out, reports in) and
the callers of pause/resume/stop (the bus owner); the process itself is one thread. A
ProducerThread is one thread; the owner's pause/resume/stop reach it under its condition. A
SyncRecord is written by the link thread or the producer thread (the periodic SYNCs) and by the
bus owner (the SYNCs it sends itself, CanBus.send_sync), read by anyone: under its lock.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Callable, Iterable

logger = logging.getLogger(__name__)

LEASE_S = 1.0            # the node's silence after which the process sends nothing (a hang)
KEEPALIVE_S = 0.1        # the node's sign of life to the process, this often
REPORT_S = 0.02          # the process reports what it sent at most this often (every SYNC of
#                          a period of 20 ms or more)
START_TIMEOUT_S = 10.0   # the process is up (connected, first SYNC sent) within this
STOP_TIMEOUT_S = 2.0     # ... and gone after `quit` within this, else it is killed
PAUSE_TIMEOUT_S = 1.0    # pause(): the process confirms within this
SEND_TIMEOUT_S = 0.5     # a frame the socket does not take within this is a send error
PERSISTENT_ERRORS = 5    # failed sends in a row: a link error (CanBus.check raises)
BUCKET_S = 1.0           # SyncRecord keeps the largest gap per second


@dataclasses.dataclass(frozen=True)
class Cyclic:
    """One frame sent every `period_s`: 'sync' or 'heartbeat'."""

    name: str
    cob_id: int
    data: bytes
    period_s: float


def set_priority(priority: int) -> str:
    """SCHED_FIFO at `priority` for the calling thread (0: the normal scheduler); '' when set,
    else why not (a refusal is no error: the producer runs on the normal scheduler)."""
    try:
        if priority:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        else:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return ''
    except (OSError, AttributeError) as exc:
        return f'SCHED_FIFO {priority} refused ({getattr(exc, "strerror", None) or exc})'


class Producer:
    """The schedule of the cyclic frames (time.monotonic): each is due one period after the one
    before; a frame late by a whole period or more is sent once and its schedule starts again
    from then, without a burst of the missed ones (a drive in interpolated position mode would
    take the second of two SYNCs back to back as "too early", FF04). `run()` sends through
    `send(cob_id, data)`, waits through `wait(timeout_s)` (the host's commands: 'pause <name>',
    'resume <name>', 'quit', 'alive'), and tells `sent(name, t)` and `failed(name, t, text)`."""

    def __init__(self, frames: Iterable[Cyclic], send: Callable[[int, bytes], None],
                 wait: Callable[[float], list[str]], sent: Callable[[str, float], None],
                 failed: Callable[[str, float, str], None],
                 paused: Callable[[str], None] = lambda name: None,
                 lease_s: float = 0.0, clock: Callable[[], float] = time.monotonic):
        self.frames = {f.name: f for f in frames}
        self.send, self.wait, self.sent, self.failed = send, wait, sent, failed
        self.on_paused = paused
        self.lease_s = lease_s         # 0: no lease (a thread of the node)
        self.clock = clock
        self.paused: set[str] = set()

    def run(self) -> None:
        now = self.clock()
        due = {name: now for name in self.frames}       # the first of each at once
        alive_at = now
        while True:
            now = self.clock()
            leased = not self.lease_s or now - alive_at <= self.lease_s
            for name, frame in self.frames.items():
                if due[name] > now:
                    continue
                if leased and name not in self.paused:
                    try:
                        self.send(frame.cob_id, frame.data)
                    except Exception as exc:  # noqa: BLE001 - no error may stop the producer
                        self.failed(name, now, f'{type(exc).__name__}: {exc}')
                    else:
                        self.sent(name, now)
                following = due[name] + frame.period_s
                due[name] = following if following > now else now + frame.period_s
            for command in self.wait(max(0.0, min(due.values()) - self.clock())):
                verb, _, name = command.partition(' ')
                if verb == 'quit':
                    return
                if verb == 'alive':
                    alive_at = self.clock()
                elif verb == 'pause' and name in self.frames:
                    self.paused.add(name)
                    self.on_paused(name)
                elif verb == 'resume' and name in self.paused:
                    self.paused.discard(name)
                    # one period after the owner's last SYNC, not at once
                    due[name] = self.clock() + self.frames[name].period_s


class SyncRecord:
    """When the SYNCs went out (time.monotonic), and the send errors of the cyclic frames."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.clock = clock
        self._lock = threading.Lock()
        self.count = 0                 # SYNCs sent
        self.errors = 0                # failed sends (SYNC and heartbeat)
        self.failing = 0               # failed sends since the last that went out
        self.last_error = ''
        self.last_t: float | None = None
        self._buckets: dict[int, float] = {}   # int(t / BUCKET_S) -> largest gap ending then

    def restart(self) -> None:
        """A new producer (the bus opened again): no gap counts across."""
        with self._lock:
            self.last_t = None
            self.failing = 0

    def sent(self, t: float) -> None:
        self.merge(1, t, t, 0.0)

    def merge(self, count: int, first_t: float, last_t: float, gap_s: float) -> None:
        """`count` SYNCs from first_t to last_t, gap_s the largest gap between them."""
        with self._lock:
            if self.last_t is not None and first_t > self.last_t:
                gap_s = max(gap_s, first_t - self.last_t)
            if gap_s > 0.0:
                key = int(last_t / BUCKET_S)
                self._buckets[key] = max(gap_s, self._buckets.get(key, 0.0))
                if len(self._buckets) > 64:
                    for old in sorted(self._buckets)[:-32]:
                        del self._buckets[old]
            self.last_t = last_t if self.last_t is None else max(self.last_t, last_t)
            self.count += count
            self.failing = 0

    def ok(self) -> None:
        """A frame other than SYNC went out: the link sends again."""
        with self._lock:
            self.failing = 0

    def failed(self, text: str, count: int = 1) -> None:
        with self._lock:
            self.errors += count
            self.failing += count
            self.last_error = text

    def gap_max_s(self, window_s: float, open_slack_s: float | None = 0.0) -> float:
        """The largest gap between two SYNCs that ended within the last window_s, and the one
        still open (now - the last SYNC, less open_slack_s: how late the record may hear of a
        SYNC; None: not counted)."""
        now = self.clock()
        with self._lock:
            first = int((now - window_s) / BUCKET_S)
            gap = max((g for k, g in self._buckets.items() if k >= first), default=0.0)
            if open_slack_s is not None and self.last_t is not None:
                gap = max(gap, now - self.last_t - open_slack_s)
            return gap


class ProducerThread:
    """The producer as a thread of the node (interfaces that take one handle per channel). The
    thread takes `priority` itself (SCHED_FIFO; 0: the normal scheduler), whoever starts it."""

    def __init__(self, name: str, frames: list[Cyclic], send: Callable[[int, bytes], None],
                 record: SyncRecord, priority: int, on_refused: Callable[[str], None],
                 on_errors: Callable[[int, str], None]):
        self.frames, self.record, self.priority = frames, record, priority
        self._send, self._on_refused, self._on_errors = send, on_refused, on_errors
        self._cv = threading.Condition()
        self._commands: list[str] = []
        self._paused_names: set[str] = set()
        self.failure = ''              # why the thread ended before stop() (a bug)
        self._stopping = False
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.native_id: int | None = None

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        self.native_id = threading.get_native_id()
        refused = set_priority(self.priority)
        if refused:
            self._on_refused(refused)
        try:
            Producer(self.frames, self._send, self._wait, self._sent, self._failed,
                     self._paused).run()
        except BaseException as exc:
            logger.exception('%s ended', self.thread.name)
            self.failure = f'the SYNC thread ended: {type(exc).__name__}: {exc}'
            raise
        if not self._stopping:
            self.failure = 'the SYNC thread ended'

    def _wait(self, timeout_s: float) -> list[str]:
        with self._cv:
            if not self._commands:
                self._cv.wait(timeout_s)
            commands, self._commands = self._commands, []
            return commands

    def _sent(self, name: str, t: float) -> None:
        if name == 'sync':
            self.record.sent(t)
        else:
            self.record.ok()

    def _failed(self, name: str, t: float, text: str) -> None:
        self.record.failed(f'{name}: {text}')
        self._on_errors(1, f'{name}: {text}')

    def _paused(self, name: str) -> None:
        with self._cv:
            self._paused_names.add(name)
            self._cv.notify_all()

    def _command(self, command: str) -> None:
        with self._cv:
            self._commands.append(command)
            self._cv.notify_all()

    def pause(self, name: str, timeout_s: float = PAUSE_TIMEOUT_S) -> bool:
        with self._cv:
            self._paused_names.discard(name)
        self._command(f'pause {name}')
        with self._cv:
            return self._cv.wait_for(lambda: name in self._paused_names, timeout_s)

    def resume(self, name: str) -> None:
        self._command(f'resume {name}')

    def refresh(self) -> None:
        pass

    def stop(self) -> None:
        self._stopping = True
        self._command('quit')
        if self.thread is not threading.current_thread():
            self.thread.join(max(f.period_s for f in self.frames) + STOP_TIMEOUT_S)


class ProducerProcess:
    """The producer as a process of its own (socketcand); the node's side of it. start() returns
    once the process has sent its first SYNC; its `link` thread keeps it alive and takes its
    reports into `record`."""

    def __init__(self, name: str, frames: list[Cyclic], host: str, port: int, channel: str,
                 record: SyncRecord, priority: int, on_refused: Callable[[str], None],
                 on_errors: Callable[[int, str], None]):
        self.name, self.record = name, record
        self.config = dict(host=host, port=port, channel=channel, priority=priority,
                           frames=[[f.name, f.cob_id, f.data.hex(), f.period_s]
                                   for f in frames])
        self._on_refused, self._on_errors = on_refused, on_errors
        self.proc: subprocess.Popen | None = None
        self._read_lock = threading.Lock()     # one reader of the process' reports at a time
        self._write_lock = threading.Lock()
        self._buffer = b''
        self._paused = threading.Condition()
        self._paused_names: set[str] = set()
        self._stopping = threading.Event()
        self.failure = ''              # why the process ended by itself
        self.link: threading.Thread | None = None
        # how late the record hears of a SYNC: the process reports every REPORT_S at most
        self.slack_s = REPORT_S if min(f.period_s for f in frames) < REPORT_S else 0.0

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def start(self) -> None:
        """Start the process and wait for its first SYNC; OSError (its reason) otherwise."""
        # -I: the standard library only, no user site or PYTHONPATH (faster, nothing injected)
        self.proc = subprocess.Popen(
            [sys.executable, '-I', os.path.abspath(__file__), json.dumps(self.config)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, close_fds=True)
        assert self.proc.stdout is not None
        os.set_blocking(self.proc.stdout.fileno(), False)
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            for line in self._read(max(0.0, deadline - time.monotonic())):
                if line.startswith('ready'):
                    refused = line[len('ready'):].strip()
                    if refused:
                        self._on_refused(refused)
                    self.link = threading.Thread(target=self._link, name=self.name, daemon=True)
                    self.link.start()
                    return
                if line.startswith('fatal '):
                    self._reap()
                    raise OSError(line[len('fatal '):])
            if self.proc.poll() is not None or time.monotonic() >= deadline:
                self._reap()
                raise OSError(f'the SYNC process did not start within {START_TIMEOUT_S:g} s'
                              f' (exit code {self.proc.returncode})')

    def _read(self, timeout_s: float) -> list[str]:
        """The complete report lines that came within timeout_s (['eof'] once the process'
        stdout closed). The wait holds no lock (health() reads too: it must not wait for the
        link thread's select); the pipe does not block, so a reader that finds nothing left by
        the other returns at once."""
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        if timeout_s > 0:
            select.select([fd], [], [], timeout_s)
        with self._read_lock:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                return []
            if not chunk:
                return ['eof']
            lines = (self._buffer + chunk).split(b'\n')
            self._buffer = lines.pop()
            out = [line.decode('ascii', 'replace') for line in lines]
            for line in out:          # taken under the lock: reports in their order
                self._take(line)
            return out

    def _take(self, line: str) -> None:
        verb, _, rest = line.partition(' ')
        if verb == 'stats':        # syncs first_t last_t gap_s others errors [error text]
            words = rest.split(' ', 6)
            syncs, others, errors = int(words[0]), int(words[4]), int(words[5])
            if syncs:
                self.record.merge(syncs, float(words[1]), float(words[2]), float(words[3]))
            elif others:
                self.record.ok()
            if errors:
                text = words[6] if len(words) > 6 else ''
                self.record.failed(text, errors)
                self._on_errors(errors, text)
        elif verb == 'paused':
            with self._paused:
                self._paused_names.add(rest)
                self._paused.notify_all()

    def _link(self) -> None:
        """Keep-alives to the process every KEEPALIVE_S, its reports into the record."""
        alive_due = 0.0
        while not self._stopping.is_set():
            now = time.monotonic()
            if now >= alive_due:
                self._write('alive')
                alive_due = now + KEEPALIVE_S
            if 'eof' in self._read(max(0.0, alive_due - time.monotonic())):
                break
        if not self._stopping.is_set():
            assert self.proc is not None
            code = self.proc.wait()
            self.failure = f'the SYNC process ended (exit code {code})'
            logger.warning('%s: %s', self.name, self.failure)

    def refresh(self) -> None:
        """Take what the process reported meanwhile (health(): a node whose threads waited for
        the GIL must not see the SYNCs of that time as missing)."""
        if self.proc is not None and self.proc.stdout is not None and not self.failure:
            with contextlib.suppress(OSError, ValueError):      # closed by stop() meanwhile
                self._read(0.0)

    def _write(self, command: str) -> None:
        with self._write_lock:
            try:
                if self.proc is not None and self.proc.stdin is not None:
                    os.write(self.proc.stdin.fileno(), command.encode('ascii') + b'\n')
            except (OSError, ValueError):      # the process is gone: the link thread says so
                pass

    def pause(self, name: str, timeout_s: float = PAUSE_TIMEOUT_S) -> bool:
        with self._paused:
            self._paused_names.discard(name)
        self._write(f'pause {name}')
        with self._paused:
            return self._paused.wait_for(lambda: name in self._paused_names, timeout_s)

    def resume(self, name: str) -> None:
        self._write(f'resume {name}')

    def stop(self) -> None:
        self._stopping.set()
        self._write('quit')
        if self.link is not None and self.link is not threading.current_thread():
            self.link.join(KEEPALIVE_S + STOP_TIMEOUT_S)
        self._reap()

    def _reap(self) -> None:
        proc = self.proc
        if proc is None:
            return
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                with contextlib.suppress(OSError):
                    pipe.close()


# ----------------------------------------------------------------------- the process itself
class SocketcandSender:
    """A socketcand client in BCM mode (linux-can/socketcand doc/protocol.md): `< open ch >`,
    then `< send id dlc data... >` per frame; the server sends this connection nothing back."""

    def __init__(self, host: str, port: int, channel: str):
        self.sock = socket.create_connection((host, port), START_TIMEOUT_S)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._expect('< hi >')
        self.sock.sendall(f'< open {channel} >'.encode('ascii'))
        self._expect('< ok >')
        self.sock.settimeout(SEND_TIMEOUT_S)

    def _expect(self, text: str) -> None:
        got = b''
        while not got.rstrip().endswith(b'>'):
            chunk = self.sock.recv(256)
            if not chunk:
                break
            got += chunk
        if got.decode('ascii', 'replace').strip() != text:
            raise OSError(f'socketcand: expected {text!r}, got {got!r}')

    def send(self, cob_id: int, data: bytes) -> None:
        words = ' '.join(f'{b:02X}' for b in data)
        self.sock.sendall(f'< send {cob_id:X} {len(data)} {words} >'.encode('ascii'))

    def drain(self) -> bool:
        """Whatever the server sent (an error reply): read and dropped. False once the server
        closed the connection (the sends fail from then on: the node reconnects)."""
        try:
            return bool(self.sock.recv(4096, socket.MSG_DONTWAIT))
        except (BlockingIOError, socket.timeout):
            return True
        except OSError:
            return False


class _ProcessReports:
    """The process' reports on stdout, written without blocking: a node that does not read
    (its threads wait for the GIL) never holds up a SYNC; what does not fit waits for the next
    report, summed up."""

    def __init__(self):
        os.set_blocking(1, False)
        self.pending = b''
        self.count, self.first_t, self.last_t, self.gap_s = 0, 0.0, 0.0, 0.0
        self.others = 0                      # frames other than SYNC sent
        self.errors, self.error_text = 0, ''
        self.prev_t: float | None = None     # the last SYNC sent (across reports)
        self.reported_at = 0.0

    def line(self, text: str) -> None:
        self.pending += text.encode('ascii', 'replace') + b'\n'
        self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        try:
            written = os.write(1, self.pending)
        except BlockingIOError:
            return
        self.pending = self.pending[written:]

    def sent(self, name: str, t: float) -> None:
        if name == 'sync':
            if self.prev_t is not None:
                self.gap_s = max(self.gap_s, t - self.prev_t)
            if not self.count:
                self.first_t = t
            self.count += 1
            self.last_t = self.prev_t = t
        else:
            self.others += 1
        self.report(t)

    def failed(self, name: str, t: float, text: str) -> None:
        self.errors += 1
        self.error_text = f'{name}: {text}'.replace('\n', ' ')
        self.report(t, force=True)

    def paused(self, name: str) -> None:
        self.prev_t = None                   # the owner sends the SYNCs from now
        self.report(time.monotonic(), force=True)
        self.line(f'paused {name}')

    def report(self, t: float, force: bool = False) -> None:
        if not force and t - self.reported_at < REPORT_S:
            return
        if self.count or self.others or self.errors:
            self.line(f'stats {self.count} {self.first_t:.6f} {self.last_t:.6f} '
                      f'{self.gap_s:.6f} {self.others} {self.errors} {self.error_text}'.rstrip())
            self.count, self.gap_s, self.others, self.errors, self.error_text = 0, 0.0, 0, 0, ''
            self.reported_at = t
        self.flush()


def main(argv: list[str]) -> int:
    """The process: argv[1] is the JSON of ProducerProcess.config. Ends at `quit` or EOF on
    stdin (the node is gone); SIGINT and SIGTERM are the node's (it ends the SYNC, after its
    orderly stop, by `quit`), so they are ignored here."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    config = json.loads(argv[1])
    reports = _ProcessReports()
    refused = set_priority(int(config['priority']))
    try:
        sender = SocketcandSender(config['host'], int(config['port']), config['channel'])
    except OSError as exc:
        reports.line(f'fatal cannot connect to socketcand {config["host"]}:{config["port"]}: '
                     f'{exc}')
        return 1
    frames = [Cyclic(name, int(cob_id), bytes.fromhex(data), float(period))
              for name, cob_id, data, period in config['frames']]
    stdin = sys.stdin.fileno()
    watched = [stdin, sender.sock]
    buffer = b''
    started = False

    def sent(name: str, t: float) -> None:
        nonlocal started
        reports.sent(name, t)
        if not started and name == 'sync':
            started = True
            reports.line(f'ready {refused}'.rstrip())

    def wait(timeout_s: float) -> list[str]:
        nonlocal buffer
        ready, _, _ = select.select(watched, [], [], timeout_s)
        if sender.sock in ready and not sender.drain():
            watched.remove(sender.sock)
        reports.flush()
        if stdin not in ready:
            return []
        chunk = os.read(stdin, 4096)
        if not chunk:
            return ['quit']              # the node is gone
        lines = (buffer + chunk).split(b'\n')
        buffer = lines.pop()
        return [line.decode('ascii', 'replace') for line in lines]

    if not any(f.name == 'sync' for f in frames):
        reports.line(f'ready {refused}'.rstrip())
    Producer(frames, sender.send, wait, sent, reports.failed, reports.paused,
             lease_s=LEASE_S).run()
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
