"""Start project executables as real processes: the harness of the tests, the demo and the
benchmarks (not part of any drive's product path; it lives with the simulators).

`Proc`: a process in its own process group, output captured to a file, waited on by evidence
(a line it prints), stopped by its own PID with SIGINT (SIGKILL only if it does not end).
Every process runs with PYTHONFAULTHANDLER: one that does not end gets SIGABRT first, and its
log then holds the stack of every thread (a hang seen once in CI is otherwise a guess).
No rclpy here.
"""

from __future__ import annotations

import os
import pathlib
import select
import signal
import socket
import subprocess
import termios
import threading
import time
import tty

from stepper_drivers.cli.ros_client import wait_for  # noqa: F401 - one definition, re-exported


def workspace_root() -> pathlib.Path:
    """The colcon workspace: STEPPER_WS, else the folder above install/ that holds this file."""
    if os.environ.get('STEPPER_WS'):
        return pathlib.Path(os.environ['STEPPER_WS'])
    for parent in pathlib.Path(__file__).resolve().parents:
        if (parent / 'install').is_dir() and (parent / 'src').is_dir():
            return parent
    return pathlib.Path.cwd()


ROOT = workspace_root()
INSTALL = ROOT / 'install'
CONFIG = ROOT / 'config'


def executable(pkg: str, exe: str) -> str:
    path = INSTALL / pkg / 'lib' / pkg / exe
    if not path.exists():
        raise FileNotFoundError(f'{path} missing: run scripts/bootstrap.sh')
    return str(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL it when the thread that started it ends (Linux
    PR_SET_PDEATHSIG; used for the main thread, i.e. the process). A test process that aborts
    cannot run its clean-up; its simulators and nodes would live on in its ROS domain and
    answer the next test run in their place."""
    import ctypes
    PR_SET_PDEATHSIG = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):   # not Linux: the normal clean-up has to do
        pass


class Proc:
    """A project executable run as its own process group, output in a log file."""

    def __init__(self, args: list[str], log_dir: pathlib.Path, name: str,
                 env: dict[str, str] | None = None):
        self.name = name
        self.log_path = log_dir / f'{name}.log'
        self.log_file = open(self.log_path, 'wb')
        self.proc = subprocess.Popen(args, stdout=self.log_file, stderr=subprocess.STDOUT,
                                     start_new_session=True,
                                     env={**os.environ, 'PYTHONFAULTHANDLER': '1',
                                          **(env or {})},
                                     # the death signal follows the starting *thread*: only
                                     # the main thread lives as long as the process
                                     preexec_fn=_die_with_parent
                                     if threading.current_thread() is threading.main_thread()
                                     else None)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        return self.log_path.read_text(errors='replace')

    def wait_line(self, text: str, timeout_s: float = 20.0) -> None:
        def seen():
            if self.proc.poll() is not None:
                raise AssertionError(f'{self.name} exited with {self.proc.returncode} before '
                                     f'printing {text!r}:\n{self.output()[-3000:]}')
            return text in self.output()
        wait_for(seen, timeout_s, f'{self.name} to print {text!r}', 0.02)

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 15.0) -> int:
        """Signal our own process group; returns the exit code."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._dump_stacks()
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)   # its children too
                except ProcessLookupError:
                    pass
                self.proc.wait(timeout=5)
                raise AssertionError(f'{self.name} did not end within {timeout_s} s of '
                                     f'signal {sig}:\n{self.output()[-12000:]}') from None
        self.log_file.close()
        return self.proc.returncode

    def _dump_stacks(self, timeout_s: float = 3.0) -> None:
        """SIGABRT to the process alone: faulthandler writes every thread's stack to its log."""
        try:
            os.kill(self.proc.pid, signal.SIGABRT)
            self.proc.wait(timeout=timeout_s)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=5)
        self.log_file.close()


def fifo_allowed(priority: int) -> bool:
    """Whether this process may put a thread on SCHED_FIFO at `priority` (root, CAP_SYS_NICE,
    an rtprio limit at least that high): the tests of owner_thread_priority expect either that
    or its refusal. Probed in a thread of its own, which then ends."""
    allowed = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            allowed.append(True)
        except OSError:
            allowed.append(False)
    thread = threading.Thread(target=probe)
    thread.start()
    thread.join()
    return allowed[0]


class SyncListener:
    """A station on a socketcand bus (the loopback broker on `port`): the broker's time stamps
    of the SYNCs (COB-ID 0x080) it relays, so a test judges the SYNC on the wire itself."""

    def __init__(self, port: int):
        import can  # (only the CAN tests and benchmarks need python-can)
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0',
                           tcp_tune=True)
        self.stamps: list[float] = []
        self.lock = threading.Lock()
        self.notifier = can.Notifier(self.bus, [self._on], 0.1)

    def _on(self, msg) -> None:
        if msg.arbitration_id == 0x080:
            with self.lock:
                self.stamps.append(msg.timestamp)

    def count(self) -> int:
        with self.lock:
            return len(self.stamps)

    def since(self, mark: int) -> list[float]:
        with self.lock:
            return list(self.stamps[mark:])

    def wait_syncs(self, count: int, mark: int = 0) -> None:
        wait_for(lambda: self.count() - mark >= count, 5.0, f'{count} SYNCs on the bus')

    def max_gap(self, mark: int = 0) -> float:
        """The largest time between two SYNCs relayed since the mark-th one [s]."""
        return max_gap(self.since(mark))

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def max_gap(stamps: list[float]) -> float:
    """The largest time between two consecutive stamps."""
    return max(b - a for a, b in zip(stamps, stamps[1:]))


class RawLine:
    """The host side of a simulated serial line, with no driver code and no pyserial: the
    symlinked pty opened raw, strings written with a CR, answers read up to their CR."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)

    def send(self, text: str) -> None:
        os.write(self.fd, text.encode('ascii') + b'\r')

    def ask(self, text: str, timeout_s: float = 0.3) -> str | None:
        """Send text + CR; the answer (CR stripped) or None when nothing comes in timeout_s."""
        self.send(text)
        return self.read(timeout_s)

    def read(self, timeout_s: float = 0.3) -> str | None:
        buf = b''
        deadline = time.monotonic() + timeout_s
        while not buf.endswith(b'\r'):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None if not buf else buf.decode()
            buf += os.read(self.fd, 256)
        return buf[:-1].decode('ascii')

    def close(self) -> None:
        os.close(self.fd)
