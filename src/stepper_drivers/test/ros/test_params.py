"""Parameter declaration and validation on a real rclpy node (no drive needed)."""

import pathlib

import pytest
import rclpy
from stepper_drivers.contract.drive import ParamSpec, Vendor
from stepper_drivers.ros.params import ParameterError, declare_all, non_ros_args

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
    return declare_with(tmp_path, text)


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


def test_a_vendors_path_bound_default_is_its_joints_in_rad_and_a_given_one_wins(tmp_path):
    """constraints.<joint>.path_bound: 0.05 rad, 0.005 m, or the vendor's own default for a
    joint in rad (Vendor.joint_defaults: the X-MIND K's 0.5 rad); a value given is taken."""
    import dataclasses

    from stepper_drivers.vendors.xmind_k import VENDOR as XMIND_K
    assert XMIND_K.joint_defaults == {'path_bound': 0.5}
    text = GOOD + '    constraints.j1.goal: 0.01\n'
    for vendor, j1 in ((VENDOR, 0.05), (dataclasses.replace(VENDOR, joint_defaults={
            'path_bound': 0.5}), 0.5)):
        f = tmp_path / 'p.yaml'
        f.write_text(text)
        args = ['x', '--ros-args', '--params-file', str(f)]
        context = rclpy.Context()
        rclpy.init(args=args, context=context)
        node = rclpy.create_node('n', context=context)
        try:
            declare_all(node, vendor, args)
        finally:
            end(node, context)
        assert node.get_parameter('constraints.j1.path_bound').value == j1
        assert node.get_parameter('constraints.axis2.path_bound').value == 0.005    # in m
    _, node = declare_with(tmp_path, text + '    constraints.j1.path_bound: 0.2\n')
    assert node.get_parameter('constraints.j1.path_bound').value == 0.2


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
    # rcl leaves an empty YAML list NOT_SET: declare_parameter returns None
    (('port: 1502', 'port: []'),
     r'parameter port: \[\] is not allowed \(allowed: an integer from 1 to 65535\)'),
    (('drives: [axis1, axis2]', 'drives: []'), r'parameter drives: no drive named'),
    (('drives: [axis1, axis2]', 'drives: ~'),
     r"parameter drives: '~' is not a list of strings \(allowed: a list of strings\)"),
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


def test_a_params_file_for_another_node_says_so(tmp_path):
    """A params file of another vendor: rd4_node started with config/xplus_mt.yaml."""
    with pytest.raises(ParameterError, match=r'parameter drives: not set, and no parameter is '
                       r'given for node /n \(a params file configures the node named by its '
                       r'top-level key: n: in the root namespace, /\*\*/n: in any, or '
                       r'/\*\*:\)'):
        declare_from(tmp_path, GOOD.replace('n:', 'other_node:', 1))


def test_non_ros_args_are_returned():
    assert non_ros_args(['exe', 'extra', '--ros-args', '-p', 'port:=1']) == ['exe', 'extra']


@pytest.mark.parametrize('text, message', [
    (None, 'cannot be read (No such file or directory)'),
    ('', 'cannot be read (Is a directory)'),
    ('n:\n  ros__parameters:\n    drives: [axis1\n', 'not a ROS 2 params file (Error '),
    ('n: 3\n', 'not a ROS 2 params file (Cannot have a value before ros__parameters at line 1)'),
])
def test_a_params_file_rcl_cannot_use_is_named(tmp_path, text, message):
    f = tmp_path / 'p.yaml'
    if text == '':
        f.mkdir()
    elif text is not None:
        f.write_text(text)
    with pytest.raises(ParameterError) as e:
        non_ros_args(['exe', '--ros-args', '--params-file', str(f)])
    assert str(e.value).startswith(f'params file {f}: {message}'), str(e.value)
    assert ' at /' not in str(e.value) and '\n' not in str(e.value)   # no C source locations


@pytest.mark.parametrize('args, message', [
    (['-p', 'port'], "Couldn't parse parameter override rule: '-p port'"),
    (['--params-file'], "Couldn't parse trailing --params-file flag"),
    (['--no-such-flag'], "unknown ROS arguments ['--no-such-flag']"),
])
def test_a_ros_argument_rcl_refuses_is_named(args, message):
    with pytest.raises(ParameterError) as e:
        non_ros_args(['exe', '--ros-args', *args])
    assert message in str(e.value) and ' at /' not in str(e.value), str(e.value)


def declare_with(tmp_path: pathlib.Path, text: str, *ros_args: str):
    f = tmp_path / 'p.yaml'
    f.write_text(text)
    args = ['x', '--ros-args', '--params-file', str(f), *ros_args]
    context = rclpy.Context()
    rclpy.init(args=args, context=context)
    node = rclpy.create_node('n', context=context)
    try:
        return declare_all(node, VENDOR, args), node
    finally:
        end(node, context)


def end(node, context) -> None:
    """Destroy the node (its DDS participant) now, then end the context. Left to the garbage
    collector, the participant of an earlier test went at an arbitrary later moment, amid the
    discovery of the next tests' participants, and Fast DDS 2.14 once deadlocked there: its
    delete_participant spinning in set_listener (cf. eProsima/Fast-DDS#6513) while a flow
    controller thread waited for a lock (a CI run hung in this file for 10 minutes).
    Descriptors and values stay readable in Python after destroy_node."""
    node.destroy_node()
    rclpy.try_shutdown(context=context)


WILD = """
/**:
  ros__parameters:
    port: 1600
    word_order: big
"""


def test_an_integer_for_a_float_parameter_and_the_precedence_of_the_arguments(tmp_path):
    cfg, node = declare_with(tmp_path, WILD + GOOD, '-p', 'drives.axis2.max_velocity:=20',
                             '-p', 'n:timeout_s:=0.25')
    assert cfg.params['port'] == 1502 and cfg.params['word_order'] == 'big'
    assert cfg.params['timeout_s'] == 0.25
    assert cfg.drives[1].params['max_velocity'] == 20.0       # -p with an integer
    assert cfg.drives[0].params['max_velocity'] == 10.0       # the file, with an integer


# (file blocks, ROS arguments after the params file): rcl's own combination decides
ORDERS = [
    (WILD + GOOD, ('-p', 'port:=7')),                # /** first: the node's block wins
    (GOOD + WILD, ()),                               # the node's block first: /** wins
    (GOOD, ('-p', 'port:=7', '-p', 'n:port:=8')),
    (GOOD, ('-p', 'n:port:=8', '-p', 'port:=7')),
    (GOOD.replace('n:', '/n:', 1), ('-p', 'other:port:=9', '-p', 'drives.axis1.unit_id:=5')),
    # a node in a namespace: a plain key is the root namespace's node; /**/n and /*/n and
    # /cell1/n are this one
    (GOOD, ('-r', '__ns:=/cell1')),
    (GOOD.replace('n:', '/**/n:', 1), ('-r', '__ns:=/cell1')),
    (GOOD.replace('n:', '/*/n:', 1), ('-r', '__ns:=/cell1')),
    (GOOD.replace('n:', '/cell1/n:', 1) + WILD, ('-r', '__ns:=/cell1')),
    (GOOD.replace('n:', '/cell2/n:', 1), ('-r', '__ns:=/cell1')),
    (GOOD.replace('n:', '/**/n:', 1), ()),
]


@pytest.mark.parametrize('text, ros_args', ORDERS)
def test_given_parameters_agrees_with_rcl(tmp_path, text, ros_args):
    """given_parameters reads the arguments as rcl and rclpy combine them. The reference is
    rclpy's private Node._parameter_overrides, read here only: the product code does not."""
    from stepper_drivers.ros.params import given_parameters
    f = tmp_path / 'p.yaml'
    f.write_text(text)
    args = ['x', '--ros-args', '--params-file', str(f), *ros_args]
    context = rclpy.Context()
    rclpy.init(args=args, context=context)
    node = rclpy.create_node('n', context=context)
    try:
        rcl = {name: p.value for name, p in node._parameter_overrides.items()}
        assert given_parameters(args, node) == rcl
    finally:
        end(node, context)


@pytest.mark.parametrize('text, ros_args, message', [
    (GOOD, ('-p', 'drive_typo:=1'), 'parameter drive_typo: unknown parameter'),
    (WILD.replace('word_order', 'word_ordr') + GOOD, (), 'parameter word_ordr: unknown parameter'),
    (GOOD, ('-p', 'drives.axis1.max_velocity:=fast'),
     r"parameter drives.axis1.max_velocity: 'fast' is not a floating point number"),
    (GOOD, ('-p', 'port:=0'), r'parameter port: 0 is out of range'),
])
def test_a_bad_ros_argument_is_named_with_its_value(tmp_path, text, ros_args, message):
    with pytest.raises(ParameterError, match=message):
        declare_with(tmp_path, text, *ros_args)
