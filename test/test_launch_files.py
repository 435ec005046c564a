"""The launch files reference only what exists, checked without importing launch (not installable
here): each file is parsed with `ast`, and every package, executable, params file and included
launch file it names is looked up in the workspace (setup.py console scripts, config/, launch/)
and in install/ (what `ros2 launch` would run)."""

import ast
import pathlib

import pytest
from rosharness import INSTALL, ROOT
import yaml

LAUNCH_DIR = ROOT / 'src' / 'stepper_drivers' / 'launch'
CONFIG_DIR = ROOT / 'config'
LAUNCH_FILES = sorted(LAUNCH_DIR.glob('*.launch.py'))
VENDORS = ('xplus_mt', 'rd4', 'xmind_k', 'vector_step')
ALLOWED_IMPORTS = ('os', 'launch', 'launch_ros', 'ament_index_python')


def console_scripts(package: str) -> set[str]:
    """Executables of a package, from the NODES list / SIMS dict in its setup.py."""
    tree = ast.parse((ROOT / 'src' / package / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name) \
                and node.targets[0].id in ('NODES', 'SIMS'):
            value = ast.literal_eval(node.value)
            return set(value)
    raise AssertionError(f'{package}/setup.py has no NODES or SIMS')


EXECUTABLES = {p: console_scripts(p) for p in ('stepper_drivers', 'stepper_sim')}


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


def calls(tree, name):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and call_name(n) == name]


def yaml_file(node) -> str | None:
    """'x.yaml' from os.path.join(config, 'x.yaml'), else None."""
    if isinstance(node, ast.Call) and call_name(node) == 'join':
        last = node.args[-1]
        if isinstance(last, ast.Constant) and str(last.value).endswith('.yaml'):
            return last.value
    return None


def node_key(yaml_name: str) -> str:
    return next(iter(yaml.safe_load((CONFIG_DIR / yaml_name).read_text())))


@pytest.fixture(params=LAUNCH_FILES, ids=[p.name for p in LAUNCH_FILES])
def launch(request):
    path = request.param
    return path, ast.parse(path.read_text(), str(path))


def test_every_vendor_and_the_demo_have_a_launch_file():
    names = {p.name for p in LAUNCH_FILES}
    assert {f'{v}.launch.py' for v in VENDORS} | {'demo.launch.py'} <= names


def test_imports_and_entry_point(launch):
    path, tree = launch
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            for m in mods:
                assert m.split('.')[0] in ALLOWED_IMPORTS, f'{path.name} imports {m}'
    funcs = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert 'generate_launch_description' in funcs


def test_packages_executables_and_params_files_exist(launch):
    check_references(*launch)


def check_references(path: pathlib.Path, tree: ast.AST) -> None:
    for c in calls(tree, 'get_package_share_directory') + calls(tree, 'get_package_prefix'):
        pkg = const(c.args[0])
        assert (ROOT / 'src' / pkg / 'package.xml').exists(), f'{path.name}: no package {pkg}'
        assert (INSTALL / pkg).is_dir(), f'{pkg} not built (run scripts/bootstrap.sh)'
    for c in calls(tree, 'Node'):
        pkg, exe = const(kw(c, 'package')), const(kw(c, 'executable'))
        assert exe in EXECUTABLES[pkg], f'{path.name}: {pkg} has no executable {exe}'
        assert (INSTALL / pkg / 'lib' / pkg / exe).exists(), f'{exe} not installed'
        params = kw(c, 'parameters')
        assert params is not None, f'{path.name}: {exe} without a params file'
    for c in calls(tree, 'ExecuteProcess'):
        # os.path.join(get_package_prefix('pkg'), 'lib', 'pkg', 'exe')
        join = kw(c, 'cmd').elts[0]
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
            if n.value.endswith('.launch.py'):
                assert (LAUNCH_DIR / n.value).exists(), f'{path.name}: {n.value} missing'


def test_node_names_match_their_params_files(launch):
    """A params file applies to the node named by its top key: renaming a node in a launch file
    without its YAML would start it on defaults."""
    path, tree = launch
    defaults = {const(c.args[0]): yaml_file(kw(c, 'default_value'))
                for c in calls(tree, 'DeclareLaunchArgument')}
    for c in calls(tree, 'Node'):
        name = const(kw(c, 'name'))
        for p in kw(c, 'parameters').elts:
            yaml_name = yaml_file(p)
            if yaml_name is None and isinstance(p, ast.Call) and \
                    call_name(p) == 'LaunchConfiguration':
                yaml_name = defaults[const(p.args[0])]
            assert yaml_name, f'{path.name}: {name}: parameters not a config file'
            assert node_key(yaml_name) == name, f'{yaml_name} configures {node_key(yaml_name)}'


@pytest.mark.parametrize('vendor', VENDORS)
def test_vendor_launch_starts_its_simulator_only_with_sim_true(vendor):
    tree = ast.parse((LAUNCH_DIR / f'{vendor}.launch.py').read_text())
    args = {const(c.args[0]): c for c in calls(tree, 'DeclareLaunchArgument')}
    assert const(kw(args['sim'], 'default_value')) == 'false'
    started = {const(kw(c, 'executable')): c for c in calls(tree, 'Node')}
    assert f'{vendor}_node' in started and f'{vendor}_sim' in started
    assert kw(started[f'{vendor}_node'], 'condition') is None
    for exe, c in started.items():
        if exe.endswith('_sim'):
            cond = ast.unparse(kw(c, 'condition'))
            assert 'sim' in cond and ('IfCondition' in cond or cond == 'sim'), cond
    # the simulator's link (port, pty, CAN port) is the one the node's params file opens
    sim_yaml = yaml.safe_load((CONFIG_DIR / f'{vendor}_sim.yaml').read_text())
    node_yaml = yaml.safe_load((CONFIG_DIR / f'{vendor}.yaml').read_text())
    sim_p = next(iter(sim_yaml.values()))['ros__parameters']
    node_p = next(iter(node_yaml.values()))['ros__parameters']
    key = 'can' if vendor == 'vector_step' else 'port'
    sim_link = sim_p[key]['port'] if key == 'can' else sim_p['port']
    node_link = node_p[key]['port'] if key == 'can' else node_p['port']
    assert sim_link == node_link


def test_demo_launch_includes_every_vendor_with_sim():
    tree = ast.parse((LAUNCH_DIR / 'demo.launch.py').read_text())
    included = {const(c.args[0]) for c in calls(tree, 'include')}
    assert included == {f'{v}.launch.py' for v in VENDORS}
    text = (LAUNCH_DIR / 'demo.launch.py').read_text()
    assert "launch_arguments={'sim': 'true'}" in text


def test_vector_step_broker_port_is_the_params_files_port():
    tree = ast.parse((LAUNCH_DIR / 'vector_step.launch.py').read_text())
    cmd = kw(calls(tree, 'ExecuteProcess')[0], 'cmd').elts
    port = int(const(cmd[cmd.index(next(e for e in cmd if isinstance(e, ast.Constant)
                                        and e.value == '--port')) + 1]))
    node_p = next(iter(yaml.safe_load(
        (CONFIG_DIR / 'vector_step.yaml').read_text()).values()))['ros__parameters']
    assert node_p['can']['port'] == port


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
