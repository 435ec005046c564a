"""Serial line timing helpers (Modbus over Serial Line V1.02 §2.5.1.1 numbers)."""

import time

import pytest
from stepper_sim.core.line_timing import LineTiming, char_time_s, frame_time_s, t15_s, t35_s


def test_character_frame_and_silence_times():
    assert char_time_s(9600) == pytest.approx(11 / 9600)
    assert char_time_s(9600, bits_per_char=10) == pytest.approx(10 / 9600)
    assert frame_time_s(8, 19200) == pytest.approx(8 * 11 / 19200)       # FC03 request
    assert t35_s(9600) == pytest.approx(3.5 * 11 / 9600)                 # 4.01 ms
    assert t35_s(19200) == pytest.approx(3.5 * 11 / 19200)               # 2.005 ms
    assert t35_s(38400) == 0.00175 and t35_s(115200) == 0.00175          # fixed above 19200
    assert t15_s(115200) == 0.00075 and t15_s(9600) == pytest.approx(1.5 * 11 / 9600)
    with pytest.raises(ValueError, match='baud must be > 0'):
        char_time_s(0)


def test_line_timing_switch_and_delay():
    assert LineTiming(baud=9600).reply_delay_s(8, 9) == 0.0              # off by default
    line = LineTiming(baud=9600, enabled=True)
    expected = (8 + 9) * 11 / 9600 + 3.5 * 11 / 9600
    assert line.reply_delay_s(8, 9) == pytest.approx(expected)
    t0 = time.monotonic()
    line.wait_before_reply(8, 9, since_s=t0)
    assert time.monotonic() - t0 >= expected - 1e-4
