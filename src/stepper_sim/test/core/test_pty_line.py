"""PtyLine on a real pty: the symlink, bytes both ways, link faults, cut and restore, clean stop.

The line under test is a minimal subclass that answers every CR-terminated string with the same
string in upper case; the client is plain os.open/os.read on the symlink (no project code).
"""

import os
import select
import time

import pytest
from stepper_sim.core.pty_line import LINK_FAULTS, PtyLine, PtyLineBackend
from stepper_sim.harness import wait_for


class UpperLine(PtyLine):
    """Answers each CR-terminated string in upper case; counts the model ticks."""

    label = 'test'
    thread_name = 'test-line'
    tick_s = 0.01

    def __init__(self, link_path, **kwargs):
        super().__init__(link_path, **kwargs)
        self.buf = bytearray()
        self.ticks = 0

    def _received_bytes(self, data, now):
        self.buf += data
        while b'\r' in self.buf:
            n = self.buf.index(b'\r') + 1
            frame, self.buf[:] = bytes(self.buf[:n]), self.buf[n:]
            if self.tap:
                self.tap('rx', frame, now)
            with self.lock:
                reply, _extra_s = self._apply_link_faults(frame.upper())
            if reply is not None:
                self._send(reply)

    def _tick(self, now):
        self.ticks += 1


class Client:
    """The driver's side: the slave pty opened through the symlink."""

    def __init__(self, path):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)

    def ask(self, data: bytes, timeout_s: float = 1.0) -> bytes:
        os.write(self.fd, data)
        got = b''
        deadline = time.monotonic() + timeout_s
        while not got.endswith(b'\r') and time.monotonic() < deadline:
            readable, _, _ = select.select([self.fd], [], [], deadline - time.monotonic())
            if readable:
                got += os.read(self.fd, 256)
        return got

    def close(self):
        os.close(self.fd)


@pytest.fixture
def line(tmp_path):
    seen = []
    ln = UpperLine(tmp_path / 'line.tty', tap=lambda d, data, t: seen.append((d, data)))
    ln.seen = seen
    yield ln
    ln.stop()


def test_symlink_appears_and_bytes_round_trip(line):
    assert not os.path.lexists(line.link_path)
    assert line.start() == line.link_path
    assert os.path.islink(line.link_path)
    assert os.readlink(line.link_path) == line.tty_name and line.tty_name.startswith('/dev/pts/')
    c = Client(line.link_path)
    try:
        assert c.ask(b'01qa\r') == b'01QA\r'     # raw: no echo, CR not turned into LF
    finally:
        c.close()
    assert ('rx', b'01qa\r') in line.seen
    # the tap hears a write after it is made (the client may have read it already)
    wait_for(lambda: ('tx', b'01QA\r') in line.seen, 2.0, 'the tap to see the reply')
    assert line.counters['pty_opened'] == 1
    wait_for(lambda: line.ticks >= 3, 2.0, 'the model ticks')


def test_counted_fault_ends_by_itself(line):
    line.start()
    c = Client(line.link_path)
    try:
        assert line.set_link_fault('no_reply', 2) == 'no_reply for the next 2 replies'
        assert c.ask(b'a\r', 0.2) == b''
        assert c.ask(b'b\r', 0.2) == b''
        assert c.ask(b'c\r') == b'C\r'
        assert line.faults.mode == 'ok'
        assert line.set_link_fault('corrupt_reply') == 'corrupt_reply for every reply'
        assert c.ask(b'd\r', 0.2) != b'D\r'
        assert c.ask(b'e\r', 0.2) != b'E\r'
        line.set_link_fault('link_ok')
        assert c.ask(b'f\r') == b'F\r'
    finally:
        c.close()
    with pytest.raises(ValueError, match="unknown link fault 'unplug'.*no_reply.*link_ok"):
        line.set_link_fault('unplug')
    assert 'link_ok' in LINK_FAULTS


def test_cut_removes_the_link_and_restore_brings_a_new_pty(line):
    line.start()
    c = Client(line.link_path)
    assert c.ask(b'before\r') == b'BEFORE\r'
    assert line.set_link_fault('cut').startswith('pty closed')
    wait_for(lambda: not os.path.lexists(line.link_path), 2.0, 'the link to go')
    assert line._master is None
    with pytest.raises(OSError):                   # the old pty is hung up: EIO
        os.write(c.fd, b'lost\r')
    c.close()
    with pytest.raises(FileNotFoundError):
        Client(line.link_path)
    line.set_link_fault('link_ok')
    wait_for(lambda: os.path.islink(line.link_path), 2.0, 'the link back')
    assert line.counters['pty_opened'] == 2
    assert os.readlink(line.link_path) == line.tty_name
    c = Client(line.link_path)
    try:
        assert c.ask(b'after\r') == b'AFTER\r'
    finally:
        c.close()


def test_stop_removes_only_its_own_link_and_ends_the_thread(line, tmp_path):
    line.start()
    thread = line._thread
    line.stop()
    assert not thread.is_alive()
    assert not os.path.lexists(line.link_path)
    # a link another line has taken over is left alone
    other = UpperLine(tmp_path / 'shared.tty')
    other.start()
    os.unlink(other.link_path)
    os.symlink('/dev/null', other.link_path)
    other.stop()
    assert os.readlink(other.link_path) == '/dev/null'


def test_backend_shares_life_cycle_names_and_lookup(tmp_path):
    line = UpperLine(tmp_path / 'b.tty')
    line.by_name = {'axis1': 'model 1', 'axis2': 'model 2'}
    backend = PtyLineBackend(line)
    try:
        assert backend.start() == f'{line.link_path} -> {line.tty_name}'
        assert list(backend.drive_names) == ['axis1', 'axis2']
        assert line.device('axis2') == 'model 2'
        with pytest.raises(ValueError, match=r"unknown drive 'axis9' \(drives: axis1, axis2\)"):
            line.device('axis9')
    finally:
        backend.stop()
    assert not os.path.lexists(line.link_path)
