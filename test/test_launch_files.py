"""The launch files reference only what exists and start what they should, checked without
importing launch (not installable here).

One generic file, driver.launch.py (vendor:=<key>), starts every vendor from the vendor table;
<key>.launch.py are links to it and demo.launch.py includes it once per vendor. Each file is
parsed with `ast` for its imports and constant references. Then `ros2_launch()` (rigs_launch.py)
runs the files on stand-ins for the launch classes they use, with launch's own rules for launch
configurations: every executable a run starts is looked up in the workspace (setup.py console
scripts) and in install/ (what `ros2 launch` would run), every params file in config/ and
install/, and the tests check which processes start with which params files.
"""

import ast
import pathlib

import pytest
from rigs_launch import CONFIG_DIR, EXECUTABLES, LAUNCH_DIR, ros2_launch
from rosharness import INSTALL, ROOT
from stepper_drivers.vendors.table import BY_KEY, KEYS
import yaml

LAUNCH_FILES = sorted(LAUNCH_DIR.glob('*.launch.py'))
SOURCES = [p for p in LAUNCH_FILES if not p.is_symlink()]     # the links are driver.launch.py
VENDORS = KEYS
ALLOWED_PACKAGES = ('os', 'launch', 'launch_ros', 'ament_index_python')    # and their modules
ALLOWED_MODULES = ('stepper_drivers.vendors.table',)  # plain data: no rclpy, no vendor module


def call_name(call: ast.Call) -> str:
    f = call.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ''


def kw(call: ast.Call, name: str):
    for k in call.keywords:
        if k.arg == name:
            return k.value
    return None


def const(node) -> str:
    assert isinstance(node, ast.Constant) and isinstance(node.value, str), \
        f'line {getattr(node, "lineno", "?")}: expected a string literal, got {ast.dump(node)}'
    return node.value


def literal(node) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def calls(tree, name):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and call_name(n) == name]


def yaml_file(node) -> str | None:
    """'x.yaml' from os.path.join(config, 'x.yaml'), else None."""
    if isinstance(node, ast.Call) and call_name(node) == 'join':
        last = node.args[-1]
        if isinstance(last, ast.Constant) and str(last.value).endswith('.yaml'):
            return last.value
    return None


@pytest.fixture(params=SOURCES, ids=[p.name for p in SOURCES])
def launch(request):
    path = request.param
    return path, ast.parse(path.read_text(), str(path))


def test_one_generic_file_and_a_link_to_it_per_shipped_vendor():
    assert {p.name for p in SOURCES} == {'driver.launch.py', 'demo.launch.py'}
    links = {p.name: p.readlink() for p in LAUNCH_FILES if p.is_symlink()}
    assert links == {f'{v}.launch.py': pathlib.Path('driver.launch.py') for v in VENDORS}


def test_imports_and_entry_point(launch):
    path, tree = launch
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            for m in mods:
                assert m in ALLOWED_MODULES or m.split('.')[0] in ALLOWED_PACKAGES, \
                    f'{path.name} imports {m}'
    funcs = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert 'generate_launch_description' in funcs


def test_packages_executables_and_params_files_exist(launch):
    check_references(*launch)


def check_references(path: pathlib.Path, tree: ast.AST) -> None:
    for c in calls(tree, 'get_package_share_directory') + calls(tree, 'get_package_prefix'):
        pkg = const(c.args[0])
        assert (ROOT / 'src' / pkg / 'package.xml').exists(), f'{path.name}: no package {pkg}'
        assert (INSTALL / pkg).is_dir(), f'{pkg} not built (run scripts/bootstrap.sh)'
    # Names computed at launch time (driver.launch.py's, from the vendor table) are checked when
    # the model runs the file (check_installed); here the literal ones.
    for c in calls(tree, 'Node') + calls(tree, 'LifecycleNode'):
        if not literal(kw(c, 'executable')):
            continue
        pkg, exe = const(kw(c, 'package')), const(kw(c, 'executable'))
        assert exe in EXECUTABLES[pkg], f'{path.name}: {pkg} has no executable {exe}'
        assert (INSTALL / pkg / 'lib' / pkg / exe).exists(), f'{exe} not installed'
        params = kw(c, 'parameters')
        assert params is not None, f'{path.name}: {exe} without a params file'
    for c in calls(tree, 'ExecuteProcess'):
        # os.path.join(get_package_prefix('pkg'), 'lib', 'pkg', 'exe')
        join = kw(c, 'cmd').elts[0]
        if not (isinstance(join, ast.Call) and all(map(literal, join.args[1:]))):
            continue
        prefix_call, lib, pkg, exe = join.args
        pkg_name = const(prefix_call.args[0])
        assert (const(lib), const(pkg)) == ('lib', pkg_name)
        assert const(exe) in EXECUTABLES[pkg_name]
        assert (INSTALL / pkg_name / 'lib' / pkg_name / const(exe)).exists()
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str):
            if n.value.endswith('.yaml'):
                assert (CONFIG_DIR / n.value).exists(), f'{path.name}: config/{n.value} missing'
                installed = INSTALL / 'stepper_drivers' / 'share' / 'stepper_drivers' / \
                    'config' / n.value
                assert installed.exists(), f'{n.value} not installed (bootstrap)'
            if n.value.endswith('.launch.py') and n.value != '.launch.py':
                assert (LAUNCH_DIR / n.value).exists(), f'{path.name}: {n.value} missing'


@pytest.mark.parametrize('vendor', VENDORS)
def test_the_simulator_opens_the_link_the_node_opens(vendor):
    """The simulator's link (port, pty, CAN port) is the one the node's params file opens, and a
    helper's --port (the CAN broker) is that port too."""
    row = BY_KEY[vendor]
    links = []
    for name in (row.sim_params_file, row.params_file):
        p = next(iter(yaml.safe_load((CONFIG_DIR / name).read_text()).values()))
        p = p['ros__parameters']
        for part in row.link_param.split('.'):
            p = p[part]
        links.append(p)
    assert links[0] == links[1], (row.link_param, links)
    for name, *args in row.sim_helpers:
        if '--port' in args:
            assert int(args[args.index('--port') + 1]) == links[1], (name, args, links)


def test_launch_files_are_installed():
    for p in LAUNCH_FILES:
        installed = INSTALL / 'stepper_drivers' / 'share' / 'stepper_drivers' / 'launch' / p.name
        assert installed.exists(), f'{p.name} not installed (run scripts/bootstrap.sh)'


@pytest.mark.parametrize('text, missing', [
    ("Node(package='stepper_drivers', executable='no_such_node', name='x', parameters=[])",
     'no executable no_such_node'),
    ("Node(package='stepper_sim', executable='rd4_sim', name='rd4_sim', "
     "parameters=[os.path.join(config, 'rd4_simm.yaml')])", 'config/rd4_simm.yaml missing'),
    ("include('rd5.launch.py')", 'rd5.launch.py missing'),
])
def test_a_wrong_reference_is_caught(text, missing):
    with pytest.raises(AssertionError, match=missing):
        check_references(pathlib.Path('bad.launch.py'), ast.parse(text))


# ------------------------------------------------------------------ launch, as it runs the files
# the helper processes the launch files start with sim:=true, with their arguments
HELPERS = {'vector_step': {'socketcand_broker': ['--port', '29536']}}


def test_the_demo_starts_every_simulator_and_node_each_with_its_own_params_file():
    assert ros2_launch('demo.launch.py') == {
        **{f'{v}_{kind}': [f'config/{v}{suffix}.yaml'] for v in VENDORS
           for kind, suffix in (('sim', '_sim'), ('node', ''))},
        **{h: args for v in VENDORS for h, args in HELPERS.get(v, {}).items()}}


@pytest.mark.parametrize('vendor', VENDORS)
@pytest.mark.parametrize('how', ['link', 'vendor:='])
def test_a_vendor_launch_alone_starts_its_node_and_with_sim_true_its_simulator(vendor, how):
    """`ros2 launch stepper_drivers <vendor>.launch.py` and `driver.launch.py vendor:=<vendor>`
    start the same."""
    def launch(**arguments):
        if how == 'link':
            return ros2_launch(f'{vendor}.launch.py', **arguments)
        return ros2_launch('driver.launch.py', vendor=vendor, **arguments)

    node = {f'{vendor}_node': [f'config/{vendor}.yaml']}
    sim = {f'{vendor}_sim': [f'config/{vendor}_sim.yaml'], **HELPERS.get(vendor, {})}
    assert launch() == node
    assert launch(sim='true') == {**sim, **node}
    assert list(launch(sim='true'))[-2:] == [f'{vendor}_sim', f'{vendor}_node']  # helpers first
    assert launch(sim='false', params_file='/cell/line1.yaml') == \
        {f'{vendor}_node': ['/cell/line1.yaml']}
    # lifecycle:=true: the managed node instead, named like the plain one, same params file
    assert launch(lifecycle='true') == {f'{vendor}_lifecycle_node': [f'config/{vendor}.yaml']}
    assert launch(lifecycle='true', sim='true') == \
        {**sim, f'{vendor}_lifecycle_node': [f'config/{vendor}.yaml']}


@pytest.mark.parametrize('arguments, error', [
    ({}, "vendor:='' is not a vendor of stepper_drivers"),
    ({'vendor': 'rd5'}, "vendor:='rd5' is not a vendor of stepper_drivers \\(one of: "
                        + ', '.join(VENDORS)),
])
def test_the_generic_file_without_a_known_vendor_says_which_there_are(arguments, error):
    with pytest.raises(RuntimeError, match=error):
        ros2_launch('driver.launch.py', **arguments)


def test_a_vendor_argument_overrides_the_file_name():
    assert ros2_launch('rd4.launch.py', vendor='xmind_k') == \
        {'xmind_k_node': ['config/xmind_k.yaml']}


# A demo of before: per-vendor launch files, each with its own params_file default, included one
# after the other, unscoped.
OLD_VENDOR_FILE = """
import os
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory('stepper_drivers'), 'config')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=os.path.join(config, '{key}.yaml')),
        Node(package='stepper_drivers', executable='{key}_node', name='{key}_node',
             parameters=[LaunchConfiguration('params_file')]),
    ])
"""
UNSCOPED_DEMO = """
import os
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource


def generate_launch_description():
    share = get_package_share_directory('stepper_drivers')
    return LaunchDescription([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(share, 'launch', f'old_{v}.launch.py')))
        for v in ('xplus_mt', 'rd4')])
"""


def test_the_model_passes_an_unscoped_include_s_arguments_on_as_launch_does():
    """What `ros2 launch stepper_drivers demo.launch.py` did on a real Jazzy install with a demo
    of before: the first file's params_file default reached every later vendor's node."""
    sources = {'demo.launch.py': UNSCOPED_DEMO,
               **{f'old_{key}.launch.py': OLD_VENDOR_FILE.replace('{key}', key)
                  for key in ('xplus_mt', 'rd4')}}
    with pytest.raises(AssertionError,
                       match='rd4_node started with config/xplus_mt.yaml, which configures '
                             'xplus_mt_node'):
        ros2_launch('demo.launch.py', sources)


def test_the_links_included_unscoped_would_all_start_the_first_vendor():
    """Why demo.launch.py scopes each include: the vendor a link's name gives is a launch
    argument default, and the first one set stays for every later unscoped include."""
    text = UNSCOPED_DEMO.replace("f'old_{v}.launch.py'", "f'{v}.launch.py'")
    with pytest.raises(AssertionError, match='xplus_mt_node started twice'):
        ros2_launch('demo.launch.py', {'demo.launch.py': text})


def test_the_model_scopes_a_group_as_launch_does():
    text = """
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, SetLaunchConfiguration
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('f', default_value='outer.yaml'),
        GroupAction([SetLaunchConfiguration('f', 'inner.yaml'),
                     Node(executable='a', parameters=[LaunchConfiguration('f')])]),
        Node(executable='b', parameters=[LaunchConfiguration('f')]),
        GroupAction([Node(executable='c', parameters=[LaunchConfiguration('f')])],
                    scoped=False, launch_configurations={'f': 'leaked.yaml'}),
        Node(executable='d', parameters=[LaunchConfiguration('f')]),
        GroupAction([Node(executable='e', parameters=[LaunchConfiguration('f', default='-')])],
                    forwarding=False),
    ])
"""
    assert ros2_launch('t.launch.py', {'t.launch.py': text}) == {
        'a': ['inner.yaml'], 'b': ['outer.yaml'], 'c': ['leaked.yaml'], 'd': ['leaked.yaml'],
        'e': ['-']}
