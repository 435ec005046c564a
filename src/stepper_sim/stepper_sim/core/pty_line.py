"""A simulated serial line on a pseudo-terminal: the plumbing the serial simulators share.

`PtyLine` owns an `os.openpty()` pair. The slave side stays open (a driver that opens and closes
the port never gets EIO) and is handed to the driver through a symlink at `link_path`, replaced
atomically when the pty is re-created. One thread reads the master side and hands the bytes to
the subclass, which frames them and answers through `_send()`. The link faults of `LinkFaults`
apply to the answers; 'cut' closes the pty and removes the link until 'link_ok' (the driver sees
the port vanish, as when a USB adapter is unplugged). No rclpy.

What a protocol brings (rd4_sim: RTU frames ended by silence, checked by CRC; xmind_k_sim: ASCII
strings ended by CR) lives in the subclass, through four hooks:
- `_received_bytes(data, now)`: bytes from the master (the driver) as they arrive;
- `_service(now)`: once per pass of the loop (frames ended by silence, replies that are due);
- `_deadline_s()`: when `_service` must run next at the latest (None: no hurry);
- `_tick(now)`: every `tick_s`, the device models' own update (motion, watchdogs).
"""

from __future__ import annotations

import logging
import os
import select
import termios
import threading
import time
import tty
from typing import Any, Callable, Sequence

from .faults import CORRUPT_REPLY, CUT, LATE_REPLY, MODES, NO_REPLY, OK, LinkFaults, invert_bytes

logger = logging.getLogger(__name__)

LINK_FAULTS = (NO_REPLY, LATE_REPLY, CORRUPT_REPLY, CUT, 'link_ok')   # inject_fault kinds
READ_CHUNK_BYTES = 4096


class PtyLine:
    """A serial line on a pty; subclasses frame the bytes and answer (see the module doc).

    `tap(direction, data, t)` sees every received frame the subclass reports ('rx') and every
    write to the master ('tx'). `lock` guards the device models and the fault budget; hooks
    that touch the models take it.
    """

    label = 'serial'          # names the line in the log
    thread_name = 'pty-line'
    reply_words = ('reply', 'replies')    # what set_link_fault's message calls the answers
    tick_s = 0.05

    def __init__(self, link_path: str | os.PathLike, *,
                 corrupt: Callable[[bytes], bytes] = invert_bytes, pty_baud: int | None = None,
                 line_timing: bool = False,
                 tap: Callable[[str, bytes, float], None] | None = None):
        self.link_path = str(link_path)
        self.pty_baud = pty_baud          # set on the slave side, so the master's can be compared
        self.line_timing = line_timing
        self.tap = tap
        self.faults = LinkFaults(corrupt=corrupt)
        self.fault_budget = 0              # replies the current fault still affects (0: all)
        self.lock = threading.RLock()
        self.counters: dict[str, int] = {'pty_opened': 0}
        self.by_name: dict[str, Any] = {}    # drive name -> device model (set by the subclass)
        self.tty_name = ''
        self._master: int | None = None
        self._slave: int | None = None
        self._wake_r, self._wake_w = os.pipe()
        self._thread: threading.Thread | None = None
        self._stopping = False
        self.faults.add_listener(lambda _mode, _delay_s: self._wake())

    # ---------------------------------------------------------------------------- hooks
    def _received_bytes(self, data: bytes, now: float) -> None:
        raise NotImplementedError

    def _service(self, now: float) -> None:
        pass

    def _deadline_s(self) -> float | None:
        return None

    def _tick(self, now: float) -> None:
        pass

    def _settings(self) -> str:
        """The line's settings for the log line of every (re-)opened pty."""
        return f'line timing {"on" if self.line_timing else "off"}'

    # ------------------------------------------------------------------------ life cycle
    def start(self) -> str:
        """Open the pty and start the line thread; returns the link path."""
        with self.lock:
            self._open_pty()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self.link_path

    def stop(self) -> None:
        self._stopping = True
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self.lock:
            self._close_pty()
            self._unlink()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b'x')
        except OSError:
            pass

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)          # no echo, no CR/LF translation (research/transports.md §C)
        if self.pty_baud is not None:
            attrs = termios.tcgetattr(slave)
            attrs[4] = attrs[5] = getattr(termios, f'B{self.pty_baud}')
            termios.tcsetattr(slave, termios.TCSANOW, attrs)
        self._master, self._slave = master, slave   # slave kept open: no EIO while unplugged
        self.tty_name = os.ttyname(slave)
        tmp = f'{self.link_path}.{os.getpid()}.tmp'
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.tty_name, tmp)
        os.replace(tmp, self.link_path)
        self.counters['pty_opened'] += 1
        logger.info('%s line on %s -> %s (%s)', self.label, self.link_path, self.tty_name,
                    self._settings())

    def _unlink(self) -> None:
        """Remove the link if it is still ours (another line may have taken the path)."""
        try:
            if os.path.islink(self.link_path) and os.readlink(self.link_path) == self.tty_name:
                os.unlink(self.link_path)
        except OSError:
            pass

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def device(self, name: str) -> Any:
        """The device model of one drive, by its name."""
        try:
            return self.by_name[name]
        except KeyError:
            raise ValueError(f'unknown drive {name!r} (drives: {", ".join(self.by_name)})') \
                from None

    # --------------------------------------------------------------------------- faults
    def set_link_fault(self, kind: str, count: int = 0, delay_s: float = 0.0) -> str:
        """One of LINK_FAULTS; `count` replies affected (0: until link_ok), `delay_s` for
        late_reply. Returns what happens, for the inject_fault service's message."""
        mode = OK if kind == 'link_ok' else kind
        if mode not in MODES:
            raise ValueError(f'unknown link fault {kind!r} (allowed: {", ".join(LINK_FAULTS)})')
        with self.lock:
            self.fault_budget = max(0, int(count)) if mode not in (OK, CUT) else 0
            self.faults.set(mode, delay_s)
        if mode == CUT:
            return 'pty closed (the driver sees the port vanish) until link_ok'
        if mode == OK:
            return 'link ok' + ('; pty re-created' if self._master is None else '')
        one, many = self.reply_words
        return f'{kind} for ' + (f'the next {count} {many}' if count > 0 else f'every {one}')

    def _apply_link_faults(self, reply: bytes) -> tuple[bytes | None, float]:
        """The current fault applied to one reply: (bytes to send or None, extra delay in s).
        A counted fault ends by itself after its last reply. Call with `lock` held."""
        mode = self.faults.mode
        reply, extra_s = self.faults.apply_to_reply(reply)
        if mode != OK and self.fault_budget > 0:
            self.fault_budget -= 1
            if self.fault_budget == 0:
                self.faults.set(OK)
        return reply, extra_s

    def _apply_cut(self) -> None:
        with self.lock:
            cut = self.faults.mode == CUT
            if cut and self._master is not None:
                self._close_pty()
                # No link to a dead pts: its number may be given to another process's pty.
                self._unlink()
                logger.info('link cut: pty closed')
            elif not cut and self._master is None and not self._stopping:
                self._open_pty()

    # ----------------------------------------------------------------------------- loop
    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stopping:
            now = time.monotonic()
            timeout = max(0.0, next_tick - now)
            deadline = self._deadline_s()
            if deadline is not None:
                timeout = min(timeout, max(0.0, deadline - now))
            fds = [self._wake_r] + ([self._master] if self._master is not None else [])
            try:
                readable, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                readable = []
            now = time.monotonic()
            if self._wake_r in readable:
                os.read(self._wake_r, READ_CHUNK_BYTES)
                self._apply_cut()
            if self._master is not None and self._master in readable:
                try:
                    data = os.read(self._master, READ_CHUNK_BYTES)
                except OSError:
                    data = b''
                if data:
                    self._received_bytes(data, now)
            self._service(now)
            if now >= next_tick:
                self._tick(now)
                next_tick = now + self.tick_s

    def _send(self, data: bytes) -> None:
        """Write to the master side (to the driver); nothing while the link is cut."""
        if self._master is None:
            return
        try:
            os.write(self._master, data)
        except OSError as exc:
            logger.debug('write to pty: %s', exc)
            return
        if self.tap:
            self.tap('tx', data, time.monotonic())


class PtyLineBackend:
    """What the `sim_node.SimBackend` of every pty line shares (duck-typed: no rclpy here);
    the simulator's subclass adds true positions, faults and inputs of its devices."""

    def __init__(self, line: PtyLine):
        self.line = line

    def start(self) -> str:
        path = self.line.start()
        return f'{path} -> {self.line.tty_name}'

    def stop(self) -> None:
        self.line.stop()

    @property
    def drive_names(self) -> Sequence[str]:
        return list(self.line.by_name)
