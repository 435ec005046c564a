"""What the serial links set on a port they opened (protocol/serial_port.py): low-latency mode
(one warning naming the latency_timer file where a USB adapter keeps a long timer) and, with
`rs485: true`, the kernel's RS-485 mode. Run on real ptys opened by the real links
(ModbusRtuBus for the RD4, AsciiLine/XmindKBus for the X-MIND K); a pty has neither a latency
timer nor the RS-485 ioctl, so where a test needs a port that has them, it replaces that one
pyserial method (or the sysfs directory) and nothing else."""

import logging
import os

import pytest
import serial
from stepper_drivers.contract.drive import LinkError
from stepper_drivers.protocol import serial_port
from stepper_drivers.protocol.ascii_line import AsciiLine, LineError
from stepper_drivers.protocol.modbus_rtu import ModbusRtuBus
from stepper_drivers.vendors import rd4, xmind_k

LOGGER = 'stepper_drivers.protocol.serial_port'


@pytest.fixture
def pty():
    """The path of a pty's device end (its other end stays open during the test)."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield path
    os.close(slave)
    os.close(master)


def rtu_bus(path, **kwargs):
    return ModbusRtuBus(path, 19200, 'N', 2, timeout_s=0.05, retries=0, **kwargs)


def xmind_bus(path, **params):
    return xmind_k.make_bus({'port': path, 'timeout_s': 0.03, 'retries': 0, **params})


def links(path, **kwargs):
    """The RD4's and the X-MIND K's serial link on `path`, not opened yet."""
    return [rtu_bus(path, **kwargs), AsciiLine(path, **kwargs)]


def fake_usb_adapter(tmp_path, monkeypatch, pty_path, timer_ms):
    """A sysfs usb-serial directory in which `pty_path` is a USB port with this latency
    timer; returns the latency_timer file."""
    devices = tmp_path / 'usb-serial' / 'devices'
    timer = devices / os.path.basename(os.path.realpath(pty_path)) / 'latency_timer'
    timer.parent.mkdir(parents=True)
    timer.write_text(f'{timer_ms}\n')
    monkeypatch.setattr(serial_port, 'USB_SERIAL_DEVICES', str(devices))
    return str(timer)


def warnings_of(caplog):
    return [r.getMessage() for r in caplog.records
            if r.name == LOGGER and r.levelno >= logging.WARNING]


def test_each_link_asks_for_low_latency_and_says_nothing_on_a_pty(pty, monkeypatch, caplog):
    asked = []
    refuse = serial.Serial.set_low_latency_mode        # on a pty: ValueError (ENOTTY)

    def recorded(self, on):
        asked.append(on)
        return refuse(self, on)
    monkeypatch.setattr(serial.Serial, 'set_low_latency_mode', recorded)
    caplog.set_level(logging.DEBUG, LOGGER)
    for link in links(pty):
        link.open()
        assert link.is_open
        link.close()
    assert asked == [True, True]
    assert warnings_of(caplog) == []


def test_a_usb_port_that_refuses_low_latency_gets_one_warning_naming_its_timer(
        pty, tmp_path, monkeypatch, caplog):
    timer = fake_usb_adapter(tmp_path, monkeypatch, pty, 16)
    caplog.set_level(logging.WARNING, LOGGER)
    for link in links(pty) + links(pty):      # two links, each reconnecting: one warning
        link.open()
        link.close()
    (line,) = warnings_of(caplog)
    assert line.startswith(f'{pty}: the USB adapter holds every reply for its latency timer '
                           '(16 ms) and low-latency mode could not be set (Failed to update '
                           'ASYNC_LOW_LATENCY flag')
    assert f'echo 1 > {timer}' in line and 'udev rule' in line and '\n' not in line


def test_a_usb_port_whose_driver_keeps_a_long_timer_gets_the_warning(
        pty, tmp_path, monkeypatch, caplog):
    timer = fake_usb_adapter(tmp_path, monkeypatch, pty, 16)
    monkeypatch.setattr(serial.Serial, 'set_low_latency_mode', lambda self, on: None)
    caplog.set_level(logging.WARNING, LOGGER)
    rtu_bus(pty).open()
    (line,) = warnings_of(caplog)
    assert '(16 ms)' in line and 'the driver kept the timer' in line and timer in line


def test_a_usb_port_at_1_ms_gets_no_warning(pty, tmp_path, monkeypatch, caplog):
    fake_usb_adapter(tmp_path, monkeypatch, pty, 1)      # a udev rule set it already
    caplog.set_level(logging.WARNING, LOGGER)
    for link in links(pty):
        link.open()
        link.close()
    assert warnings_of(caplog) == []


def test_rs485_on_a_port_that_refuses_it_fails_naming_the_parameter(pty):
    for link, error in ((rtu_bus(pty, rs485=True), LinkError),
                        (AsciiLine(pty, rs485=True), LineError),
                        (xmind_bus(pty, rs485=True), LinkError)):
        with pytest.raises(error) as e:
            link.open()
        assert str(e.value).startswith(f'parameter rs485: true, but {pty} refuses RS-485 mode '
                                       '(Failed to set RS485 mode: '), str(e.value)
        assert 'rs485: false' in str(e.value) and '\n' not in str(e.value)
        assert not link.is_open


def test_rs485_true_sets_the_kernel_rs485_mode_on_the_opened_port(pty, monkeypatch):
    applied = []       # what pyserial hands the TIOCSRS485 ioctl, on a port that accepts it
    monkeypatch.setattr(serial.Serial, '_set_rs485_mode',
                        lambda self, settings: applied.append((self.is_open, settings)))
    bus, line = rtu_bus(pty, rs485=True), AsciiLine(pty, rs485=True)
    bus.open()
    line.open()
    for port in (bus._serial, line._port):
        mode = port.rs485_mode
        assert isinstance(mode, serial.rs485.RS485Settings)
        assert mode.rts_level_for_tx is True and mode.rts_level_for_rx is False
    assert [(opened, s) for opened, s in applied] == [(True, bus._serial.rs485_mode),
                                                      (True, line._port.rs485_mode)]
    bus.close()
    line.close()
    for link in links(pty):                    # rs485: false (the default) leaves it alone
        link.open()
        assert (link._serial if isinstance(link, ModbusRtuBus) else link._port).rs485_mode \
            is None
        link.close()
    assert len(applied) == 2


def test_the_rs485_bus_parameter_reaches_the_links(pty):
    assert rd4.make_bus({'port': pty, 'baudrate': 19200, 'parity': 'N',
                         'rs485': True}).rs485 is True
    assert rd4.make_bus({'port': pty, 'baudrate': 19200, 'parity': 'N'}).rs485 is False
    assert xmind_bus(pty, rs485=True).line.rs485 is True
    assert xmind_bus(pty).line.rs485 is False
    for vendor in (rd4.VENDOR, xmind_k.VENDOR):
        (spec,) = [p for p in vendor.params if p.name == 'rs485']
        assert spec.scope == 'bus' and spec.default is False
