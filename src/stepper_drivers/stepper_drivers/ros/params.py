"""Parameter declaration and validation for every vendor node.

Each parameter is declared with a description and a range (rclpy checks ranges at declaration,
params file included). The rules between parameters are one pure function, `validate(params)`
(the common rules here, then the vendor module's `validate`), on every parameter of the node by
name: start-up runs it on the declared values, `DriveNode.on_set_parameters` on the current
values with a `ros2 param set` change applied (BusConfig.validate). Anything wrong ends start-up
with one `ParameterError` line naming the parameter, the value and what is allowed. The result is
plain dataclasses; the node keeps reading the runtime-changeable values (profile, limits, rates)
from the node, so `ros2 param set` takes effect at the next command.

What the ROS arguments give the node (for int-as-float, unknown names and the values in error
messages) is read from the arguments themselves (`given_parameters`), not from rclpy's private
`Node._parameter_overrides`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from typing import Any, Callable, Iterable, Mapping, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args
import yaml

from ..contract import param_rules
from ..contract.drive import ParamSpec, Vendor
from ..contract.units import UnitConversion

INF = float('inf')


class ParameterError(Exception):
    """A bad parameter value or params file; str() is the one line shown to the user."""


# rcl appends the C source location of each error frame: ", at /project/src/parse.c:782"
_RCL_LOCATION = re.compile(r',? at \S+\.c:\d+')
_RCL_PARAMS_FILE = re.compile(r"Couldn't parse params file: '--params-file (.*)'\. Error: (.*)")


def non_ros_args(argv: Sequence[str]) -> list[str]:
    """argv without its ROS arguments (rclpy's remove_ros_args); a params file that cannot be
    read or parsed, or a ROS argument rcl refuses, raises ParameterError naming it.

    rcl parses every --params-file already here; rclpy.init would parse them again and raise
    RCLError after logging its own error line, so an executable calls this first.
    """
    try:
        return remove_ros_args(list(argv))
    except _rclpy.UnknownROSArgsError as e:
        problem = f'unknown ROS arguments {e}'
    except _rclpy.RCLInvalidROSArgsError as e:
        problem = _ros_args_problem(str(e))
    raise ParameterError(problem)


def _ros_args_problem(rcl_error: str) -> str:
    text = _RCL_LOCATION.sub('', rcl_error)
    match = _RCL_PARAMS_FILE.search(text)
    if match is None:
        return text
    path, why = match.groups()
    try:
        with open(path, 'rb'):
            pass
    except OSError as e:
        return f'params file {path}: cannot be read ({e.strerror})'
    return f'params file {path}: not a ROS 2 params file ({why})'


# Values as rcl reads a params file: YAML scalars without the null resolver ('~' is the string
# '~' to rcl, and a message should show what the file says).
class _RclYamlLoader(yaml.SafeLoader):
    pass


_RclYamlLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != 'tag:yaml.org,2002:null']
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}


def _ros_arguments(args: Sequence[str]) -> Iterable[tuple[str, str]]:
    """(flag, value) of every --params-file and -p/--param inside --ros-args ... [--]."""
    inside = False
    it = iter(args)
    for token in it:
        if token == '--ros-args':
            inside = True
        elif token == '--' and inside:
            inside = False
        elif inside and token in ('--params-file', '-p', '--param'):
            value = next(it, None)
            if value is not None:
                yield token, value


def _flatten(values: Any, prefix: str = '') -> dict[str, Any]:
    if not isinstance(values, dict):
        return {}
    out = {}
    for key, value in values.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def _params_file_blocks(data: Any, path: str = '') -> Iterable[tuple[str, dict]]:
    """(node key with a leading '/', ros__parameters) of a params file, nested namespaces
    joined ('/ns: {node: ...}' is '/ns/node')."""
    if not isinstance(data, dict):
        return
    for key, value in data.items():
        if not isinstance(value, dict):
            continue
        name = f'{path}/{str(key).strip("/")}'
        if 'ros__parameters' in value:
            yield name, value['ros__parameters']
        else:
            yield from _params_file_blocks(value, name)


def given_parameters(args: Sequence[str], node: Node) -> dict[str, Any]:
    """The parameter values the ROS arguments in `args` give `node`, by full name.

    Sources: every --params-file (its `/**:` and `<node>:` blocks) and -p [node:]name:=value.
    As rcl and rclpy combine them (checked against them in test_params.py): each source adds to
    the entry of its node key ('/**' for -p without a node name), entries in the order they
    first appear, and the entries for `/**` and the node's fully qualified name are applied in
    that order, a later entry winning. rcl has parsed the same arguments already (non_ros_args,
    rclpy.init) and its values are the ones declared; these are for what rclpy does not tell
    publicly: which names were given, the value a type or range error names, and an integer
    given for a float parameter.
    """
    entries: dict[str, dict[str, Any]] = {}
    for flag, value in _ros_arguments(args):
        if flag == '--params-file':
            try:
                with open(value, encoding='utf-8') as f:
                    data = yaml.load(f, Loader=_RclYamlLoader)
            except (OSError, yaml.YAMLError):
                continue            # rcl refused it already (non_ros_args names it)
            for key, block in _params_file_blocks(data):
                entries.setdefault(key, {}).update(_flatten(block))
            continue
        rule, sep, text = value.partition(':=')
        if not sep:
            continue
        target, _colon, name = rule.rpartition(':')
        try:
            parsed = yaml.load(text, Loader=_RclYamlLoader)
        except yaml.YAMLError:
            parsed = text
        entries.setdefault('/' + target.strip('/') if target else '/**', {})[name] = parsed
    given: dict[str, Any] = {}
    fqn = node.get_fully_qualified_name()
    for key, values in entries.items():
        if _node_key_matches(key, fqn):
            given.update(values)
    return given


def _node_key_matches(key: str, fqn: str) -> bool:
    """Whether a params file's node key applies to the node `fqn`, as rcl matches it: a key
    without a leading slash is in the root namespace, `/*` stands for one name and `/**` for
    any number of them (`/**/xplus_mt_node` is that node in any namespace)."""
    if key in ('/**', fqn):
        return True
    pattern = re.escape(key).replace(r'/\*\*', '(?:/[^/]+)*').replace(r'/\*', '/[^/]+')
    return re.fullmatch(pattern, fqn) is not None


@dataclasses.dataclass(frozen=True)
class P:
    """A parameter of the common contract (docs/interface.md)."""

    name: str
    default: Any
    description: str
    min_value: float | None = None
    max_value: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True


# Bus-level parameters every node has; the vendor adds its transport settings.
BUS_PARAMS = (
    P('timeout_s', 0.5, 'answer timeout of one transaction on the bus [s]', 0.001, 60.0),
    P('publish_rate_hz', 50.0, 'rate of polling the drives and publishing joint_states, status '
      '[Hz]',
      0.1, 1000.0, read_only=False),
    P('command_timeout_s', 0.5, 'velocity watchdog: a drive running from velocity_command stops '
      'when no new command arrives within this time; a velocity published longer ago than this '
      'when it arrives is refused [s]', 0.01, 3600.0, read_only=False),
    P('position_command_max_age_s', 1.0, 'a position_command or joint_command position '
      'published longer ago than this when it arrives (its DDS source timestamp against this '
      "host's clock) is refused; 0 = not checked [s]", 0.0, 3600.0, read_only=False),
    P('reconnect_period_s', 1.0, 'first retry delay after the link drops; doubles up to 8x [s]',
      0.05, 600.0),
    P('diagnostics_rate_hz', 1.0, 'rate of /diagnostics, at most publish_rate_hz (the bus owner '
      'sends it after a poll cycle) [Hz]', 0.1, 50.0),
    P('status_rate_hz', 1.0, 'least rate of ~/<drive>/status: it is published at the poll '
      'that sees a change (state, position, velocity, alarms, refusals...) and at least this '
      'often otherwise [Hz]', 0.1, 1000.0, read_only=False),
    P('joint_command_shared', False, 'joint_command carries the joints of other nodes too (one '
      'ros2_control block for several nodes): names this node does not have are ignored, told '
      'once each; false: a warning every 5 s names them', read_only=False),
    P('owner_thread_priority', 10, 'real-time priority (SCHED_FIFO, 1..99) of the bus owner '
      'threads, so that a command reaches the wire without waiting for the scheduler on a '
      "loaded machine (as ros2_control's controller_manager asks for); 0 = the normal "
      'scheduler. Needs CAP_SYS_NICE or an rtprio limit (/etc/security/limits.conf); refused: '
      'one warning, and the normal scheduler', 0, 99),
    # The defaults of follow_joint_trajectory goals, as JointTrajectoryController's parameters
    # of the same names (a goal's own tolerances replace them: docs/interface.md)
    P('constraints.goal_time', 0.0, 'follow_joint_trajectory: how long after the last point '
      'of a goal the joints may take to come within their goal tolerances before the goal '
      'fails (GOAL_TOLERANCE_VIOLATED) and they stop; 0 = no limit: until every joint stands '
      "still (at most 10 s), then checked. A goal's goal_time_tolerance > 0 replaces it [s]",
      0.0, 3600.0, read_only=False),
    P('constraints.stopped_velocity_tolerance', 0.01, 'follow_joint_trajectory: at the end '
      "of a goal each joint stands (its drive's moving flag) or moves no faster than this; "
      "0 = not checked. A goal's goal_tolerance velocity > 0 replaces it for its joint "
      '[rad/s or m/s]', 0.0, INF, read_only=False),
)

# Per-joint parameters, declared as constraints.<joint>.<param> (the joint names of the
# drives): JointTrajectoryController's per-joint constraints. `goal` defaults to one step of
# the joint's drive (declare_joint_params).
JOINT_PARAMS = (
    P('trajectory', 0.0, 'follow_joint_trajectory path tolerance: while a goal runs, the joint '
      'farther than this from the plan (at the time its position was true) fails the goal '
      "(PATH_TOLERANCE_VIOLATED) and stops its joints; 0 = not checked. A goal's "
      'path_tolerance position replaces it [rad or m]', 0.0, INF, read_only=False),
    P('goal', 0.0, 'follow_joint_trajectory goal tolerance: at the end of a goal the joint '
      "within this of the last point; 0 = not checked; default one step of the joint's drive. "
      "A goal's goal_tolerance position replaces it [rad or m]", 0.0, INF, read_only=False),
    P('path_bound', 0.05, 'follow_joint_trajectory and joint_trajectory: the farthest the '
      "node's plan may pass from any point of a trajectory (points merged into longer segments "
      'where the bus needs them, velocity-continuous segments) where neither the goal '
      "(path_tolerance position) nor constraints.<joint>.trajectory gives one; a trajectory "
      'the bus cannot carry within it is rejected before anything moves. 0 = not bounded; '
      'default 0.05 rad (X-MIND K 0.5 rad: docs/moveit.md), 0.005 m for unit m [rad or m]',
      0.0, INF, read_only=False),
)
# path_bound's default for a joint in m (the rad default, 0.05, would be 5 cm)
PATH_BOUND_M = 0.005

# Per-drive parameters every node has, declared as drives.<name>.<param>.
DRIVE_PARAMS = (
    P('joint_name', '', 'joint name in joint_states and joint_command (default: the drive name)'),
    P('steps_per_rev', 200.0, 'motor steps (micro-steps) per motor revolution', 1.0, 1e9),
    P('gear_ratio', 1.0, 'motor revolutions per output revolution', 1e-9, 1e9),
    P('unit', 'rad', "joint unit: 'rad' (rotary) or 'm' (linear, needs lead_m)",
      choices=('rad', 'm')),
    P('lead_m', 0.0, 'linear travel per output revolution for unit m [m]', 0.0, 1e3),
    P('min_position', -1e9, 'lowest position a command may ask for [rad or m]', -INF, INF,
      read_only=False),
    P('max_position', 1e9, 'highest position a command may ask for [rad or m]', -INF, INF,
      read_only=False),
    P('max_velocity', 10.0, 'largest velocity a command may ask for [rad/s or m/s]', 0.0, 1e9,
      read_only=False),
    P('joint_command_max_start_offset', 0.1, 'a joint_command position that starts a stream (no '
      'joint_command position for command_timeout_s) farther than this from where the joint '
      'stands is refused: a first command of 0 from a ros2_control plugin, a stream meant for '
      'another robot [rad or m]', 0.0, INF, read_only=False),
    P('max_acceleration', 100.0, 'largest acceleration/deceleration of a profile '
      '[rad/s^2 or m/s^2]',
      0.0, 1e12, read_only=False),
    P('profile_velocity', 1.0, 'velocity of position moves [rad/s or m/s]', 0.0, 1e9,
      read_only=False),
    P('profile_acceleration', 10.0, 'acceleration of moves and velocity runs [rad/s^2 or m/s^2]',
      0.0, 1e12, read_only=False),
    P('profile_deceleration', 10.0, 'deceleration of moves, velocity runs and stops '
      '[rad/s^2 or m/s^2]', 0.0, 1e12, read_only=False),
    P('homing.method', 35, "homing method number in the drive's own numbering", -128, 127,
      read_only=False),
    P('homing.offset', 0.0, 'position of the home point after homing [rad or m]', -INF, INF,
      read_only=False),
    P('homing.speed_search', 0.5, 'speed while searching the switch [rad/s or m/s]', 0.0, 1e9,
      read_only=False),
    P('homing.speed_zero', 0.1, 'speed while searching the zero/index [rad/s or m/s]', 0.0, 1e9,
      read_only=False),
    P('homing.acceleration', 10.0, 'homing acceleration [rad/s^2 or m/s^2]', 0.0, 1e12,
      read_only=False),
    P('homing.timeout_s', 60.0, 'the home service fails (and stops the drive) after this time [s]',
      0.1, 3600.0, read_only=False),
    P('auto_enable', False, 'enable the drive at start-up (target = actual position first)'),
    P('disable_on_shutdown', True, 'disable the power stage when the node ends'),
    P('allow_raw_write', False, 'allow write_register (raw writes can change anything)'),
)

# Parameters rclpy declares on every node itself.
IMPLICIT_PARAMS = ('use_sim_time', 'start_type_description_service')


def _descriptor(p: P | ParamSpec) -> ParameterDescriptor:
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = 'one of: ' + ', '.join(p.choices)
    if isinstance(p.default, bool):
        return d
    if isinstance(p.default, int) and (p.min_value is not None or p.max_value is not None):
        d.integer_range = [IntegerRange(
            from_value=int(p.min_value if p.min_value is not None else -2**63),
            to_value=int(p.max_value if p.max_value is not None else 2**63 - 1), step=0)]
    elif isinstance(p.default, float) and (p.min_value is not None or p.max_value is not None):
        d.floating_point_range = [FloatingPointRange(
            from_value=float(p.min_value if p.min_value is not None else -INF),
            to_value=float(p.max_value if p.max_value is not None else INF), step=0.0)]
    return d


def _allowed(p: P | ParamSpec) -> str:
    if p.choices:
        return 'one of ' + ', '.join(p.choices)
    if isinstance(p.default, bool):
        return 'true or false'
    if isinstance(p.default, list):
        return 'a list of strings'
    kind = 'an integer' if isinstance(p.default, int) else 'a number'
    lo = '' if p.min_value is None else f' from {p.min_value:g}'
    hi = '' if p.max_value is None else f' to {p.max_value:g}'
    return kind + lo + hi


_TYPE_NAMES = {ParameterType.PARAMETER_BOOL: 'a boolean',
               ParameterType.PARAMETER_INTEGER: 'an integer',
               ParameterType.PARAMETER_DOUBLE: 'a floating point number',
               ParameterType.PARAMETER_STRING: 'a string',
               ParameterType.PARAMETER_STRING_ARRAY: 'a list of strings'}


def declare(node: Node, full_name: str, p: P | ParamSpec, default: Any = None,
            given: Mapping[str, Any] | None = None) -> Any:
    """Declare one parameter; return its value or raise ParameterError (one line).

    `given`: what the ROS arguments give the node (given_parameters)."""
    given = {} if given is None else given
    default = p.default if default is None else default
    if isinstance(p.default, float) and isinstance(default, int):
        default = float(default)    # a vendor default written as 12800 for a float parameter
    got = given.get(full_name, default)
    try:
        try:
            value = node.declare_parameter(full_name, default, _descriptor(p)).value
        except InvalidParameterTypeException:
            if not (isinstance(default, float) and type(got) is int):
                raise
            # YAML '10' for a float parameter: accept it as 10.0 instead of failing on the type.
            got = float(got)
            value = node.declare_parameter(full_name, got, _descriptor(p),
                                           ignore_override=True).value
    except InvalidParameterValueException:
        raise ParameterError(
            f'parameter {full_name}: {got!r} is out of range (allowed: {_allowed(p)})') from None
    except InvalidParameterTypeException:
        want = _TYPE_NAMES.get(Parameter.Type.from_parameter_value(default).value, 'valid')
        raise ParameterError(f'parameter {full_name}: {got!r} is not {want} '
                             f'(allowed: {_allowed(p)})') from None
    except ParameterUninitializedException:
        raise ParameterError(f'parameter {full_name} must be set') from None
    if value is None:
        # rcl cannot type an empty YAML list ([]): it leaves the parameter NOT_SET.
        if isinstance(default, list):
            return []
        raise ParameterError(f'parameter {full_name}: [] is not allowed (allowed: '
                             f'{_allowed(p)})')
    if p.choices and value not in p.choices:
        raise ParameterError(f'parameter {full_name}: {value!r} is not allowed '
                             f'(allowed: {_allowed(p)})')
    if isinstance(value, float) and math.isnan(value):
        raise ParameterError(f'parameter {full_name}: NaN is not allowed ({_allowed(p)})')
    return value


@dataclasses.dataclass
class DriveConfig:
    name: str
    joint_name: str
    conversion: UnitConversion
    params: dict[str, Any]   # every parameter of this drive, common and vendor, without prefix


Rules = Callable[[Mapping[str, Any]], list[str]]


def drive_errors(prefix: str, values: Mapping[str, Any]) -> list[str]:
    """Cross-field rules of one drive that ranges cannot express."""
    errors = []
    if values['min_position'] >= values['max_position']:
        errors.append(
            f"parameter {prefix}min_position: {values['min_position']} must be below "
            f"{prefix}max_position ({values['max_position']})")
    for name in ('profile_velocity', 'homing.speed_search', 'homing.speed_zero'):
        if values[name] > values['max_velocity']:
            errors.append(
                f'parameter {prefix}{name}: {values[name]} exceeds {prefix}max_velocity '
                f"({values['max_velocity']})")
    for name in ('profile_acceleration', 'profile_deceleration', 'homing.acceleration'):
        if values[name] > values['max_acceleration']:
            errors.append(
                f'parameter {prefix}{name}: {values[name]} exceeds {prefix}max_acceleration '
                f"({values['max_acceleration']})")
    try:
        UnitConversion(values['steps_per_rev'], values['gear_ratio'], values['unit'],
                       values['lead_m'])
    except ValueError as e:
        errors.append(f'parameter {prefix}{e}')
    return errors


def drives_list_errors(names: Sequence[str]) -> list[str]:
    """The drives list: at least one name, each once, each a valid name."""
    if not names:
        return ['parameter drives: no drive named (allowed: a list of one or more drive names, '
                'each with its drives.<name>.* parameters)']
    if len(set(names)) != len(names):
        return [f'parameter drives: {list(names)} names a drive twice']
    return [f'parameter drives: {n!r} is not a valid name (allowed: letters, digits and _, '
            'starting with a letter)'
            for n in names if not n.replace('_', '').isalnum() or not n[0].isalpha()]


def validate(params: Mapping[str, Any], vendor_validate: Rules | None = None) -> list[str]:
    """Every rule between parameters, on all parameters of a node by name (param_rules): the
    common ones (drives list, per drive limits against profiles, units, unique joint names),
    then the vendor's `validate`. Pure: builds no bus or drive, changes nothing. One line per
    broken rule; [] when the parameters are good."""
    names = param_rules.drive_names(params)
    errors = drives_list_errors(names)
    if errors:
        return errors
    joints = []
    for name in names:
        values = param_rules.drive_params(params, name)
        errors += drive_errors(f'drives.{name}.', values)
        joints.append(values['joint_name'] or name)
    if len(set(joints)) != len(joints):
        errors.append(f'parameter drives.*.joint_name: {joints} names a joint twice')
    if vendor_validate is not None:
        errors += vendor_validate(params)
    return errors


@dataclasses.dataclass
class BusConfig:
    params: dict[str, Any]   # common and vendor bus parameters
    drives: list[DriveConfig]
    # the rules the parameters met at start-up; run-time changes must meet them too
    validate: Rules = validate


def current_values(node: Node) -> dict[str, Any]:
    """Every declared parameter of `node` by name (rclpy's public get_parameters_by_prefix)."""
    return {name: p.value for name, p in node.get_parameters_by_prefix('').items()}


def declare_all(node: Node, vendor: Vendor, args: Sequence[str] = (),
                vendor_validate: Rules | None = None) -> BusConfig:
    """Declare the common and the vendor parameters from the ROS arguments `args` (the argv
    given to rclpy.init), then check them with `validate(params, vendor_validate)`; raise
    ParameterError on the first bad one."""
    given = given_parameters(args, node)
    bus_specs = [s for s in vendor.params if s.scope == 'bus']
    drive_specs = [s for s in vendor.params if s.scope == 'drive']
    bus = {p.name: declare(node, p.name, p, given=given) for p in (*BUS_PARAMS, *bus_specs)}
    drive_names = declare(node, 'drives', P('drives', [''], 'names of the drives on this bus'),
                          given=given)
    drive_names = [n for n in drive_names if n]
    if not drive_names and not set(given) - set(IMPLICIT_PARAMS):
        # The params file has no block for this node: its top-level key names another node.
        raise ParameterError(
            f'parameter drives: not set, and no parameter is given for node '
            f'{node.get_fully_qualified_name()} (a params file configures the node named by its '
            f'top-level key: {node.get_name()}: in the root namespace, '
            f'/**/{node.get_name()}: in any, or /**:)')
    for problem in drives_list_errors(drive_names):
        raise ParameterError(problem)
    values = {}
    for name in drive_names:
        prefix = f'drives.{name}.'
        values[name] = {
            p.name: declare(node, prefix + p.name, p, vendor.drive_defaults.get(p.name), given)
            for p in (*DRIVE_PARAMS, *drive_specs)}
    declare_joint_params(node, values, given, vendor.joint_defaults)
    _refuse_unknown(node, given, drive_names)
    rules = functools.partial(validate, vendor_validate=vendor_validate)
    for problem in rules(current_values(node)):
        raise ParameterError(problem)
    drives = [DriveConfig(name, v['joint_name'] or name,
                          UnitConversion(v['steps_per_rev'], v['gear_ratio'], v['unit'],
                                         v['lead_m']), v)
              for name, v in values.items()]
    return BusConfig(bus, drives, rules)


def declare_joint_params(node: Node, drives: Mapping[str, Mapping[str, Any]],
                         given: Mapping[str, Any], rad_defaults: Mapping[str, Any] = {}
                         ) -> None:
    """constraints.<joint>.* (JOINT_PARAMS) for the joint of each drive in `drives` (drive
    name: its declared values), once per joint name (validate refuses a name used twice);
    `rad_defaults`: the vendor's own defaults for a joint in rad (Vendor.joint_defaults)."""
    for name, v in drives.items():
        joint = v['joint_name'] or name
        try:
            step = 1.0 / UnitConversion(v['steps_per_rev'], v['gear_ratio'], v['unit'],
                                        v['lead_m']).steps_per_unit
        except ValueError:
            step = 0.0                  # validate names the broken unit parameter
        for p in JOINT_PARAMS:
            full = f'constraints.{joint}.{p.name}'
            if not node.has_parameter(full):
                default = step if p.name == 'goal' else \
                    PATH_BOUND_M if p.name == 'path_bound' and v['unit'] == 'm' else \
                    rad_defaults.get(p.name)
                declare(node, full, p, default, given)


def _refuse_unknown(node: Node, given: Mapping[str, Any], drive_names: Iterable[str]) -> None:
    """A misspelt parameter in the params file would be ignored silently by rclpy: refuse it.

    Parameters of a drive that is not in `drives` are only warned about: taking a drive out of the
    list is the normal way to run without it.
    """
    names = list(drive_names)
    unlisted = set()
    for name in given:
        if node.has_parameter(name) or name in IMPLICIT_PARAMS:
            continue
        parts = name.split('.')
        if len(parts) > 2 and parts[0] == 'drives' and parts[1] not in names:
            unlisted.add(parts[1])
            continue
        raise ParameterError(f'parameter {name}: unknown parameter (drives are {names};'
                             ' see docs/interface.md for the allowed names)')
    for drive in sorted(unlisted):
        node.get_logger().warning(f'drives.{drive}.* is configured but {drive!r} is not in '
                                  f'drives {names}: ignored')
