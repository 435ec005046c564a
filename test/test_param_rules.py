"""One set of parameter rules for start-up and run time.

Each vendor's DriveNode is built in this process from its config/<vendor>.yaml (nothing opened or
spun: the constructor declares the parameters and makes the drives). A value given at start-up
(-p name:=value) and the same value set at run time (Node.set_parameters, what `ros2 param set`
calls through the parameter service) are refused with the same line: both are the pure
`validate(params)` of params.py and the vendor module. Run time builds no drive or bus (a
throwaway one would be wrong: the X-MIND K constructor records its address in the bus it is
given).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import subprocess
import sys

import pytest
from rigs_nodes import make_node
from stepper_drivers.vendors.table import BY_KEY, KEYS

# vendor, parameter, a value its rules refuse, a value they take, words of the refusal
CASES = [
    ('xplus_mt', 'drives.axis1.homing.method', 99, 35, 'is not a homing method of the X-PLUS MT'),
    ('xplus_mt', 'publish_rate_hz', 1.0, 20.0, 'watchdog_ms: 1000 ms is less than'),
    ('xplus_mt', 'drives.axis1.max_velocity', 0.5, 20.0, 'exceeds drives.axis1.max_velocity'),
    ('rd4', 'publish_rate_hz', 2.0, 20.0, 'needs publish_rate_hz >= 5'),
    ('rd4', 'drives.axis1.homing.method', 19, 35, 'is not possible on the RD4'),
    ('xmind_k', 'drives.axis1.homing.method', 35, -3, 'is not an X-MIND K method'),
    ('vector_step', 'drives.axis1.homing.method', 19, 35, 'is not a Vector Step homing method'),
]


def ros_value(value) -> str:
    return repr(value) if isinstance(value, float) else str(value)


@pytest.mark.parametrize('key, name, bad, good, words', CASES)
def test_run_time_change_is_refused_by_the_start_up_rule(offline_rclpy, key, name, bad, good,
                                                         words):
    from rclpy.parameter import Parameter
    from stepper_drivers.ros.params import ParameterError
    with pytest.raises(ParameterError) as start_up:
        make_node(key, '-p', f'{name}:={ros_value(bad)}')
    assert words in str(start_up.value), str(start_up.value)
    node = make_node(key)
    try:
        (refused,) = node.set_parameters([Parameter(name, value=bad)])
        assert not refused.successful
        assert refused.reason == str(start_up.value)
        assert node.get_parameter(name).value != bad
        (taken,) = node.set_parameters([Parameter(name, value=good)])
        assert taken.successful, taken.reason
        assert node.get_parameter(name).value == good
    finally:
        node.destroy_node()


def counting(fn, calls: list):
    def wrapper(*args, **kwargs):
        calls.append(fn.__name__)
        return fn(*args, **kwargs)
    return wrapper


def test_run_time_checks_build_nothing_and_leave_the_x_mind_k_bus_alone(offline_rclpy):
    """The X-MIND K drive records its address in bus.addresses when it is made: a check that
    makes drives can change the live bus. The run-time check makes none (it did before)."""
    from rclpy.parameter import Parameter
    from stepper_drivers.vendors import xmind_k
    calls: list[str] = []
    vendor = dataclasses.replace(xmind_k.VENDOR,
                                 make_bus=counting(xmind_k.make_bus, calls),
                                 make_drive=counting(xmind_k.make_drive, calls))
    node = make_node('xmind_k', vendor=vendor)
    try:
        assert calls == ['make_bus', 'make_drive', 'make_drive', 'make_drive']   # start-up
        calls.clear()
        drives = {name: h.drive for name, h in node.handles.items()}
        bus = drives['axis1'].bus
        addresses = dict(bus.addresses)
        results = node.set_parameters([
            Parameter('drives.axis1.homing.method', value=60),         # taken
            Parameter('drives.axis2.homing.method', value=35),         # refused
            Parameter('publish_rate_hz', value=10.0)])                 # taken
        assert [r.successful for r in results] == [True, False, True], results
        assert calls == []
        assert bus.addresses == addresses == {'axis1': 1, 'axis2': 2, 'axis3': 3}
        assert {name: h.drive for name, h in node.handles.items()} == drives
    finally:
        node.destroy_node()


def test_the_x_mind_k_rules_refuse_one_address_twice_from_the_parameters_alone():
    from stepper_drivers.vendors import xmind_k
    params = {'port': '/dev/ttyUSB0', 'drives': ['a1', 'a2'],
              'drives.a1.address': 4, 'drives.a2.address': 4}
    for d in ('a1', 'a2'):
        params.update({f'drives.{d}.homing.method': 3, f'drives.{d}.resolution': '',
                       f'drives.{d}.steps_per_rev': 2000.0})
    before = copy.deepcopy(params)
    assert xmind_k.validate(params) == [
        'parameter drives.a2.address: 04 is already used by drive a1 on /dev/ttyUSB0 '
        '(allowed: a free address 0..47)']
    assert params == before


@pytest.mark.parametrize('key', KEYS)
def test_the_rules_of_a_config_file_are_met_and_pure(offline_rclpy, key):
    """Every shipped params file meets validate(); validate changes nothing it is given."""
    from stepper_drivers.ros.params import current_values, validate
    module = importlib.import_module(BY_KEY[key].module)
    node = make_node(key)
    try:
        values = current_values(node)
    finally:
        node.destroy_node()
    before = copy.deepcopy(values)
    assert validate(values, module.validate) == []
    assert values == before


def test_vendor_modules_and_their_rules_need_no_rclpy_nor_ament():
    code = ('import sys\n'
            'from stepper_drivers.contract import param_rules\n'
            'from stepper_drivers.vendors import table as vendor_table\n'
            'import importlib\n'
            'for row in vendor_table.ROWS:\n'
            '    m = importlib.import_module(row.module)\n'
            '    assert callable(m.validate), row.key\n'
            "assert 'rclpy' not in sys.modules, 'rclpy imported'\n"
            "assert 'ament_index_python' not in sys.modules, 'ament_index_python imported'\n"
            'from stepper_drivers.vendors.vector_step import regmap\n'
            'regmap.eds_path()\n'
            "assert 'ament_index_python' not in sys.modules, 'eds_path imported ament'\n")
    subprocess.run([sys.executable, '-c', code], check=True, timeout=60)


def test_params_uses_no_private_rclpy_parameter_state():
    import inspect

    from stepper_drivers.ros import node, params
    for module in (params, node):
        source = inspect.getsource(module)
        assert '_parameter_overrides' not in source.replace('`Node._parameter_overrides`', '')
        assert '._parameters' not in source
