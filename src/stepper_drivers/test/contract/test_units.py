import math

import pytest
from stepper_drivers.contract.units import UnitConversion


def test_rotary_direct_drive():
    c = UnitConversion(12800, 1.0, 'rad')
    assert c.to_steps_int(2 * math.pi) == 12800
    assert c.from_steps(6400) == pytest.approx(math.pi)


def test_rotary_with_gear():
    c = UnitConversion(200, 10.0, 'rad')   # 10 motor turns per output turn
    assert c.to_steps_int(2 * math.pi) == 2000
    assert c.from_steps(1000) == pytest.approx(math.pi)


def test_linear_with_lead_and_gear():
    c = UnitConversion(12800, 2.0, 'm', lead_m=0.005)   # 5 mm per output turn
    assert c.to_steps_int(0.005) == 25600
    assert c.from_steps(12800) == pytest.approx(0.0025)
    assert c.to_steps(0.01) == pytest.approx(51200)   # rates convert the same way (m/s -> Hz)


def test_round_trip_is_stable():
    c = UnitConversion(12800, 3.7, 'rad')
    for steps in (-123456, -1, 0, 1, 987654):
        assert c.to_steps_int(c.from_steps(steps)) == steps


@pytest.mark.parametrize('kwargs, words', [
    (dict(steps_per_rev=0), 'steps_per_rev'),
    (dict(steps_per_rev=200, gear_ratio=0), 'gear_ratio'),
    (dict(steps_per_rev=200, unit='deg'), "unit: 'deg'"),
    (dict(steps_per_rev=200, unit='m'), 'lead_m'),
])
def test_bad_values_name_the_parameter(kwargs, words):
    with pytest.raises(ValueError, match=words):
        UnitConversion(**kwargs)
