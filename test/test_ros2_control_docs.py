"""docs/ros2_control.md matches config/ and the nodes' parameters.

The page's code blocks are parsed, not searched as text:
- ```bash: every `ros2 run` line starts a node of a vendor; one started in a namespace
  (`-r __ns:=/<ns>`) reads a params file that a `sed` line of the page makes from
  config/<vendor>.yaml, keyed `/<ns>/<vendor>_node` (the plain key applies to the root namespace
  only); one in the root namespace reads config/<vendor>.yaml;
- ```python: the launch file's Node(...) calls (ast): the same nodes, names, namespaces and files;
- ```xml: each `<ros2_control>` block (ElementTree): the plugin
  `joint_state_topic_hardware_interface/JointStateTopicSystem`, `joint_commands_topic` =
  /<ns>/joint_command and `joint_states_topic` = /<ns>/joint_states of a namespace a run line
  uses, its joints exactly the joint names of that vendor's config/<vendor>.yaml drives, in order,
  interfaces the node has (one kind of command interface in a block: the node refuses a message
  whose position[] has not one value per name; no velocity state for the X-MIND K);
- ```yaml (yaml.safe_load): the controller_manager file (joint_state_broadcaster, one
  JointTrajectoryController per block with that block's joints and interfaces it declares, JTC
  constraint keys) and MoveIt's controllers (a JTC of that file or a node's own action, with its
  joints);
- every node parameter the page names (`drives.<drive>.x`, `name: value`, a bare name that looks
  like one) exists: stepper_drivers.ros.params and the vendor modules' declarations, and
  docs/interface.md's generated tables list it.
`test_a_wrong_name_fails` edits copies of the page (a joint name, a node name, a namespace, the
plugin, a parameter) and checks that each is caught.
"""

from __future__ import annotations

import ast
import importlib
import pathlib
import re
import xml.etree.ElementTree as ET

import pytest
from stepper_drivers.ros.params import BUS_PARAMS, DRIVE_PARAMS
from stepper_drivers.vendors.table import BY_KEY, KEYS
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOC = ROOT / 'docs' / 'ros2_control.md'
INTERFACE = ROOT / 'docs' / 'interface.md'
PLUGIN = 'joint_state_topic_hardware_interface/JointStateTopicSystem'
JTC = 'joint_trajectory_controller/JointTrajectoryController'
JSB = 'joint_state_broadcaster/JointStateBroadcaster'
INTERFACES = {'position', 'velocity'}
NO_VELOCITY_STATE = {'xmind_k'}           # the drive cannot report velocity (NaN)
JTC_CONSTRAINTS = {'stopped_velocity_tolerance', 'goal_time'}
JTC_JOINT_CONSTRAINTS = {'trajectory', 'goal'}
# Names of parameters of other software that the page names in backticks: the plugin's, the
# JTC's, the controller_manager's, MoveIt's. Anything else that looks like a parameter must be
# a node parameter.
FOREIGN = {'joint_commands_topic', 'joint_states_topic', 'trigger_joint_command_threshold',
           'sum_wrapped_joint_states', 'initial_value', 'update_rate', 'rw_rate', 'goal_time',
           'stopped_velocity_tolerance', 'action_monitor_rate', 'cmd_timeout', 'resample_dt',
           'allowed_execution_duration_scaling', 'allowed_goal_duration_margin',
           'allowed_start_tolerance', 'action_ns', 'robot_description', 'gains'}
PARAM_LIKE = re.compile(r'^[a-z][a-z0-9]*(_[a-z0-9]+)*_(s|hz|shared|offset|priority|age_s|'
                        r'timeout_s|rate_hz|position|velocity|acceleration|deceleration)$')


# ------------------------------------------------------------------------------- the sources
def config(key: str) -> tuple[str, list[str], dict]:
    """(the params file's top key, the joint names of its drives in order, its parameters)."""
    data = yaml.safe_load((ROOT / 'config' / f'{key}.yaml').read_text())
    (top, block), = data.items()
    params = block['ros__parameters']
    return top, [params[f'drives.{d}'].get('joint_name') or d for d in params['drives']], params


def node_parameters() -> tuple[set[str], set[str]]:
    """(bus-level names, per-drive names) of every vendor's node."""
    bus = {p.name for p in BUS_PARAMS}
    drive = {p.name for p in DRIVE_PARAMS}
    for key in KEYS:
        for p in importlib.import_module(BY_KEY[key].module).VENDOR.params:
            (bus if p.scope == 'bus' else drive).add(p.name)
    return bus, drive


def code_blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf'^```{lang}\n(.*?)^```', text, re.S | re.M)


def vendor_of(executable: str) -> str | None:
    for key in KEYS:
        if executable in (BY_KEY[key].node, BY_KEY[key].lifecycle_node):
            return key
    return None


# ------------------------------------------------------------------------------ the checks
def check_run_lines(text: str, problems: list[str]) -> tuple[dict[str, str], dict[str, str]]:
    """({vendor: namespace}, {vendor: params file}) of the run lines in a namespace."""
    seds = {}
    for block in code_blocks(text, 'bash'):
        for line in block.splitlines():
            m = re.match(r"\s*sed 's\|\^([\w/]+):\|([\w/]+):\|' config/(\w+)\.yaml > (\S+)$",
                         line)
            if m:
                seds[m[4]] = (m[1], m[2], m[3])
    ns_of, file_of = {}, {}
    for block in code_blocks(text, 'bash'):
        for line in block.splitlines():
            m = re.search(r'ros2 run (\S+) (\S+)(.*)$', line)
            if not m or m[1] == 'controller_manager':
                continue
            pkg, exe, rest = m[1], m[2], m[3]
            key = vendor_of(exe)
            if pkg != 'stepper_drivers' or key is None:
                problems.append(f'run line {line.strip()!r}: {pkg} {exe} is no node of '
                                'stepper_drivers')
                continue
            pf = re.search(r'--params-file (\S+)', rest)
            ns = re.search(r'-r __ns:=(\S+)', rest)
            if pf is None:
                problems.append(f'run line {line.strip()!r}: no --params-file')
                continue
            top, _joints, _params = config(key)
            if ns is None:
                if pf[1] != f'config/{key}.yaml':
                    problems.append(f'run line {line.strip()!r}: a node in the root namespace '
                                    f'reads config/{key}.yaml')
                continue
            if key in ns_of:
                problems.append(f'{key}: started in two namespaces')
            ns_of[key], file_of[key] = ns[1], pf[1]
            made = seds.get(pf[1])
            if made is None:
                problems.append(f'run line {line.strip()!r}: no sed line of the page makes '
                                f'{pf[1]}')
                continue
            old, new, source = made
            want = f'{ns[1]}/{BY_KEY[key].node}'
            if (source, old, new) != (key, top, want):
                problems.append(f'{pf[1]} is made from config/{source}.yaml keyed {new!r} (from '
                                f'{old!r}); the node {exe} in {ns[1]} needs config/{key}.yaml '
                                f'with {top!r} -> {want!r}')
    return ns_of, file_of


def check_launch(text: str, ns_of: dict[str, str], file_of: dict[str, str],
                 problems: list[str]) -> None:
    seen = set()
    for block in code_blocks(text, 'python'):
        for call in ast.walk(ast.parse(block)):
            if not (isinstance(call, ast.Call) and getattr(call.func, 'id', '') == 'Node'):
                continue
            kw = {k.arg: k.value for k in call.keywords}
            if ast.literal_eval(kw.get('package', ast.Constant(''))) != 'stepper_drivers':
                continue
            exe = ast.literal_eval(kw['executable'])
            key = vendor_of(exe)
            if key is None:
                problems.append(f'launch: {exe} is no node of stepper_drivers')
                continue
            seen.add(key)
            name = ast.literal_eval(kw.get('name', ast.Constant('')))
            ns = '/' + ast.literal_eval(kw.get('namespace', ast.Constant(''))).strip('/')
            files = ast.literal_eval(kw.get('parameters', ast.List([])))
            if name != BY_KEY[key].node:
                problems.append(f'launch: {exe} named {name!r}, not {BY_KEY[key].node!r}')
            if ns != ns_of.get(key):
                problems.append(f'launch: {exe} in namespace {ns!r}, its run line in '
                                f'{ns_of.get(key)!r}')
            if files != [file_of.get(key)]:
                problems.append(f'launch: {exe} reads {files}, its run line {file_of.get(key)}')
    for key in set(ns_of) - seen:
        problems.append(f'launch: no Node for {BY_KEY[key].node}')


def check_hardware(root: ET.Element, name: str, problems: list[str]) -> str | None:
    """A block's type, rate, plugin and parameters; its namespace (None: its topics are not
    /<ns>/joint_command and /<ns>/joint_states of one namespace)."""
    if root.tag != 'ros2_control' or root.get('type') != 'system':
        problems.append(f'block {name}: not <ros2_control type="system">')
    if root.get('rw_rate') is not None and not root.get('rw_rate').isdigit():
        problems.append(f'block {name}: rw_rate {root.get("rw_rate")!r}: a positive integer')
    hw = root.find('hardware')
    plugin = hw.findtext('plugin') if hw is not None else None
    if plugin != PLUGIN:
        problems.append(f'block {name}: plugin {plugin!r}, not {PLUGIN!r}')
    params = {p.get('name'): (p.text or '').strip()
              for p in (hw.findall('param') if hw is not None else [])}
    unknown = set(params) - {'joint_commands_topic', 'joint_states_topic',
                             'trigger_joint_command_threshold', 'sum_wrapped_joint_states'}
    if unknown:
        problems.append(f'block {name}: parameters the plugin does not have: {unknown}')
    try:
        float(params.get('trigger_joint_command_threshold', ''))
    except ValueError:
        problems.append(f'block {name}: trigger_joint_command_threshold is no number')
    m = re.fullmatch(r'(/[\w/]+)/joint_command', params.get('joint_commands_topic', ''))
    ns = m[1] if m else None
    if ns is None or params.get('joint_states_topic') != f'{ns}/joint_states':
        problems.append(f'block {name}: topics {params.get("joint_commands_topic")!r} and '
                        f'{params.get("joint_states_topic")!r} are not /<ns>/joint_command '
                        'and /<ns>/joint_states of one namespace')
        return None
    return ns


def check_block_joints(root: ET.Element, name: str, ns: str, key: str,
                       problems: list[str]) -> list[tuple]:
    """A block's joints against config/<key>.yaml and the interfaces the vendor has:
    [(name, command interfaces, state interfaces)]."""
    joints = [(j.get('name'), [c.get('name') for c in j.findall('command_interface')],
               [s.get('name') for s in j.findall('state_interface')])
              for j in root.findall('joint')]
    want = config(key)[1]
    if [j for j, _c, _s in joints] != want:
        problems.append(f'block {name} ({ns}): joints {[j for j, _c, _s in joints]}, '
                        f'config/{key}.yaml has {want}')
    if len({tuple(c) for _j, c, _s in joints}) > 1:
        problems.append(f'block {name}: the joints have different command interfaces')
    for j, cmd, state in joints:
        if not cmd or not set(cmd) <= INTERFACES or 'position' not in state \
                or not set(state) <= INTERFACES:
            problems.append(f'block {name}: joint {j}: command {cmd}, state {state}')
        if key in NO_VELOCITY_STATE and 'velocity' in state:
            problems.append(f'block {name}: joint {j}: {key} reports no velocity')
    return joints


def check_urdf(text: str, ns_of: dict[str, str], problems: list[str]) -> dict[str, dict]:
    """{block name: {'key', 'joints': [(name, command interfaces, state interfaces)]}}."""
    vendor_of_ns = {ns: key for key, ns in ns_of.items()}
    out = {}
    for block in code_blocks(text, 'xml'):
        if '<ros2_control' not in block:
            continue
        root = ET.fromstring(block)
        name = root.get('name')
        ns = check_hardware(root, name, problems)
        if ns is None:
            continue
        key = vendor_of_ns.get(ns)
        if key is None:
            problems.append(f'block {name}: namespace {ns} is none a run line starts a node in '
                            f'({sorted(vendor_of_ns)})')
            continue
        joints = check_block_joints(root, name, ns, key, problems)
        if any(b['key'] == key for b in out.values()):
            problems.append(f'{key}: two blocks')
        out[name] = {'key': key, 'joints': joints}
    for key in set(ns_of) - {b['key'] for b in out.values()}:
        problems.append(f'{key}: started in {ns_of[key]} but no <ros2_control> block')
    return out


def check_jtc(name: str, p: dict, joints: list[str], block: dict, problems: list[str]) -> None:
    """A JointTrajectoryController's interfaces against its block's, and its constraints."""
    for j, cmd, state in block['joints']:
        if not set(p.get('command_interfaces', [])) <= set(cmd) or \
                not p.get('command_interfaces'):
            problems.append(f'{name}: command_interfaces {p.get("command_interfaces")}, '
                            f'{j} declares {cmd}')
        if not set(p.get('state_interfaces', [])) <= set(state) or \
                'position' not in p.get('state_interfaces', []):
            problems.append(f'{name}: state_interfaces {p.get("state_interfaces")}, {j} '
                            f'declares {state}')
    for k, v in p.get('constraints', {}).items():
        if k in joints:
            if not set(v) <= JTC_JOINT_CONSTRAINTS:
                problems.append(f'{name}: constraints.{k}: {set(v)}')
        elif k not in JTC_CONSTRAINTS:
            problems.append(f'{name}: constraints.{k} is neither a joint of it nor a JTC '
                            'constraint')


def check_controllers(text: str, blocks: dict[str, dict], problems: list[str]
                      ) -> dict[str, list[str]]:
    """{JTC name: joints} of the controller_manager file."""
    docs = [yaml.safe_load(b) for b in code_blocks(text, 'yaml')]
    cm_files = [d for d in docs if isinstance(d, dict) and 'controller_manager' in d]
    if len(cm_files) != 1:
        problems.append(f'{len(cm_files)} controller_manager files, not 1')
        return {}
    cm = cm_files[0]
    ros = cm['controller_manager']['ros__parameters']
    if not (isinstance(ros.get('update_rate'), int) and ros['update_rate'] > 0):
        problems.append(f'update_rate {ros.get("update_rate")!r}')
    types = {n: v.get('type') for n, v in ros.items() if isinstance(v, dict)}
    if JSB not in types.values():
        problems.append('no joint_state_broadcaster')
    jtcs = {}
    by_joints = {tuple(j for j, _c, _s in b['joints']): b for b in blocks.values()}
    for name, typ in types.items():
        if typ != JTC:
            continue
        p = cm.get(name, {}).get('ros__parameters')
        if p is None:
            problems.append(f'{name}: no parameters')
            continue
        joints = list(p.get('joints', []))
        jtcs[name] = joints
        block = by_joints.get(tuple(joints))
        if block is None:
            problems.append(f'{name}: joints {joints} are the joints of no <ros2_control> block')
            continue
        check_jtc(name, p, joints, block, problems)
    for bname, b in blocks.items():
        if [j for j, _c, _s in b['joints']] not in jtcs.values():
            problems.append(f'block {bname}: no JointTrajectoryController for its joints')
    return jtcs


def check_moveit(text: str, jtcs: dict[str, list[str]], problems: list[str]) -> None:
    docs = [yaml.safe_load(b) for b in code_blocks(text, 'yaml')]
    files = [d for d in docs if isinstance(d, dict) and 'moveit_simple_controller_manager' in d]
    if len(files) != 1:
        problems.append(f'{len(files)} MoveIt controller files, not 1')
        return
    m = files[0]['moveit_simple_controller_manager']
    covered = []
    for name in m['controller_names']:
        c = m.get(name, {})
        key = vendor_of(name)
        want = jtcs.get(name) or (config(key)[1] if key else None)
        if want is None:
            problems.append(f'MoveIt: {name} is neither a JTC of the controller_manager file '
                            'nor a node')
            continue
        if c.get('joints') != want:
            problems.append(f'MoveIt: {name} joints {c.get("joints")}, it has {want}')
        if (c.get('type'), c.get('action_ns')) != ('FollowJointTrajectory',
                                                   'follow_joint_trajectory'):
            problems.append(f'MoveIt: {name}: type {c.get("type")}, action_ns '
                            f'{c.get("action_ns")}')
        covered += want
    if len(covered) != len(set(covered)):
        problems.append(f'MoveIt: a joint in two controllers: {covered}')


def check_parameters(text: str, problems: list[str]) -> set[str]:
    """The node parameters the page names; each must be declared and in docs/interface.md."""
    bus, drive = node_parameters()
    interface = INTERFACE.read_text()
    named = set()
    for token in re.findall(r'`([^`\n]+)`', text):
        for m in re.finditer(r'drives\.<drive>\.([\w.]+)', token):
            named.add(m[1])
            if m[1] not in drive:
                problems.append(f'`{token}`: {m[1]} is no per-drive parameter')
            elif f'| `drives.<drive>.{m[1]}` |' not in interface:
                problems.append(f'drives.<drive>.{m[1]} is not in docs/interface.md')
        name = token.split(':')[0].strip() if re.match(r'^\w+: ', token) else token
        if PARAM_LIKE.match(name) or name in bus:
            if name in FOREIGN or name in drive and name not in bus:
                continue
            named.add(name)
            if name not in bus:
                problems.append(f'`{token}`: {name} is no node parameter')
            elif f'| `{name}` |' not in interface:
                problems.append(f'{name} is not in docs/interface.md')
    for m in re.finditer(r'-p (\w[\w.]*):=', text):
        if m[1] not in bus:
            problems.append(f'-p {m[1]}: no bus-level node parameter')
    return named


def page_problems(text: str) -> list[str]:
    problems: list[str] = []
    ns_of, file_of = check_run_lines(text, problems)
    check_launch(text, ns_of, file_of, problems)
    blocks = check_urdf(text, ns_of, problems)
    jtcs = check_controllers(text, blocks, problems)
    check_moveit(text, jtcs, problems)
    check_parameters(text, problems)
    return problems


# ------------------------------------------------------------------------------------ tests
def test_the_page_matches_config_and_the_nodes():
    assert page_problems(DOC.read_text()) == []


def test_every_vendor_has_a_block_in_its_own_namespace():
    text = DOC.read_text()
    problems: list[str] = []
    ns_of, _files = check_run_lines(text, problems)
    assert sorted(ns_of) == sorted(KEYS)
    assert len(set(ns_of.values())) == len(KEYS), ns_of
    assert {b['key'] for b in check_urdf(text, ns_of, problems).values()} == set(KEYS)
    assert problems == []


def test_the_page_names_the_streaming_parameters():
    named = check_parameters(DOC.read_text(), [])
    assert {'joint_command_shared', 'joint_command_max_start_offset', 'command_timeout_s',
            'position_command_max_age_s'} <= named, named


def _joint(key: str, i: int) -> str:
    return config(key)[1][i]


@pytest.mark.parametrize('old, new, count', [
    (f'<joint name="{_joint("xplus_mt", 1)}">', '<joint name="xplus_joint9">', 1),
    (f'<joint name="{_joint("xmind_k", 2)}">', '<joint name="xmind_joint4">', 1),
    ('joints: [vector_joint1, vector_joint2]\n    command_interfaces',
     'joints: [vector_joint2, vector_joint1]\n    command_interfaces', 1),
    ('joints: [rd4_joint1, rd4_joint2]\n\n  xmind', 'joints: [rd4_joint1, rd4_joint3]\n\n  xmind',
     1),
    ('ros2 run stepper_drivers xplus_mt_node', 'ros2 run stepper_drivers xplus_node', 1),
    ("executable='rd4_node', name='rd4_node'", "executable='rd4_node', name='rd4'", 1),
    ('s|^vector_step_node:|/vector_step/vector_step_node:|',
     's|^vector_step_node:|/vector/vector_step_node:|', 1),
    ('<param name="joint_states_topic">/rd4/joint_states</param>',
     '<param name="joint_states_topic">/joint_states</param>', 1),
    (f'<plugin>{PLUGIN}</plugin>', '<plugin>topic_based_ros2_control/TopicBasedSystem</plugin>',
     1),
    ('`joint_command_shared', '`joint_commands_shared', 1),
    ('drives.<drive>.joint_command_max_start_offset', 'drives.<drive>.max_start_offset', 1),
])
def test_a_wrong_name_fails(old, new, count):
    """A copy of the page with one name wrong is caught."""
    text = DOC.read_text()
    assert text.count(old) >= count, f'{old!r} is not on the page'
    assert page_problems(text.replace(old, new, count)) != []
