"""Parameter declaration and validation on a real rclpy node (no drive needed)."""

import pathlib

import pytest
import rclpy

from stepper_drivers.drive import ParamSpec, Vendor
from stepper_drivers.params import ParameterError, declare_all

VENDOR = Vendor(
    name='TEST', make_bus=None, make_drive=None,
    params=(ParamSpec('port', 502, 'TCP port', scope='bus', min_value=1, max_value=65535),
            ParamSpec('word_order', 'little', 'word order', scope='bus',
                      choices=('little', 'big')),
            ParamSpec('unit_id', 1, 'unit id', min_value=0, max_value=255)),
    drive_defaults={'steps_per_rev': 12800.0})

GOOD = """
n:
  ros__parameters:
    port: 1502
    drives: [axis1, axis2]
    drives.axis1:
      unit_id: 3
      joint_name: j1
      max_velocity: 10
      homing:
        method: 19
    drives.axis2:
      unit: m
      lead_m: 0.01
"""


def declare_from(tmp_path: pathlib.Path, text: str):
    f = tmp_path / 'p.yaml'
    f.write_text(text)
    context = rclpy.Context()
    rclpy.init(args=['x', '--ros-args', '--params-file', str(f)], context=context)
    node = rclpy.create_node('n', context=context)
    try:
        return declare_all(node, VENDOR), node
    finally:
        rclpy.try_shutdown(context=context)


def test_good_file_gives_config(tmp_path):
    cfg, node = declare_from(tmp_path, GOOD)
    assert cfg.params['port'] == 1502 and cfg.params['word_order'] == 'little'
    a1, a2 = cfg.drives
    assert (a1.name, a1.joint_name, a1.params['unit_id']) == ('axis1', 'j1', 3)
    assert a1.params['max_velocity'] == 10.0          # integer in YAML accepted for a float
    assert a1.params['homing.method'] == 19
    assert a1.conversion.steps_per_rev == 12800.0      # vendor default
    assert a2.joint_name == 'axis2' and a2.conversion.unit == 'm'
    assert node.describe_parameter('drives.axis1.max_velocity').description


@pytest.mark.parametrize('edit, message', [
    (('port: 1502', 'port: 70000'),
     r'parameter port: 70000 is out of range \(allowed: an integer from 1 to 65535\)'),
    (('port: 1502', "port: 'x'"), r"parameter port: 'x' is not an integer"),
    (('unit_id: 3', 'unit_id: 256'), r'parameter drives.axis1.unit_id: 256 is out of range'),
    (('lead_m: 0.01', 'lead_m: 0.0'), r'parameter drives.axis2.lead_m: 0.0 must be > 0'),
    (('unit: m', 'unit: deg'),
     r"parameter drives.axis2.unit: 'deg' is not allowed \(allowed: one of rad, m\)"),
    (('max_velocity: 10', 'max_velocity: -1'), r'drives.axis1.max_velocity: -1.0 is out of range'),
    (('max_velocity: 10', 'max_velocity: 0.5'),
     r'drives.axis1.profile_velocity: 1.0 exceeds drives.axis1.max_velocity'),
    (('drives: [axis1, axis2]', 'drives: [axis1, axis1]'), r'names a drive twice'),
    (('drives: [axis1, axis2]', 'drives: [axis1, axis2]\n    drive_typo: 1'),
     r'parameter drive_typo: unknown parameter'),
    (('joint_name: j1', 'joint_name: j1\n      max_velocty: 3.0'),
     r'drives.axis1.max_velocty: unknown parameter'),
])
def test_bad_value_is_one_line_naming_parameter_value_and_range(tmp_path, edit, message):
    with pytest.raises(ParameterError, match=message) as e:
        declare_from(tmp_path, GOOD.replace(*edit))
    assert '\n' not in str(e.value)


def test_min_above_max_is_refused(tmp_path):
    text = GOOD.replace('joint_name: j1',
                        'joint_name: j1\n      min_position: 5.0\n      max_position: 1.0')
    with pytest.raises(ParameterError, match='drives.axis1.min_position: 5.0 must be below'):
        declare_from(tmp_path, text)


def test_no_drive_is_refused(tmp_path):
    with pytest.raises(ParameterError, match='parameter drives: no drive named'):
        declare_from(tmp_path, 'n:\n  ros__parameters:\n    port: 1502\n')
