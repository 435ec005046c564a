"""docs/adding_a_vendor.md is what the code needs.

The page's code blocks (each `# file: <path>`, and the `# row:` block) are the toy vendor. This
test writes them into a temporary directory, with copies of vendors/table.py and both setup.py that
get the row appended, and shows that the table's readers pick the vendor up with no other file
edited: the console scripts of both packages, the `toy_node` executable function, stepperctl's
tables, the generic launch file and the demo's as `ros2 launch` runs them, and the node itself
(parameters declared from config/toy.yaml, the toy's validate() refusing a bad value at start-up
and at run time, a drive that answers its simulator).
"""

from __future__ import annotations

import importlib
import importlib.util
import re
import runpy
import shutil
import sys

import pytest
from rosharness import ROOT
from stepper_drivers.vendors import table as vendor_table
import yaml

DOC = ROOT / 'docs' / 'adding_a_vendor.md'
BLOCK = re.compile(r'```(?:python|yaml)\n# (file|row): (\S+)[^\n]*\n(.*?)```', re.S)
KEY = 'toy'


def doc_blocks() -> tuple[dict[str, str], str]:
    """({path: text} of the `# file:` blocks, the row's text)."""
    files, rows = {}, []
    for kind, path, body in BLOCK.findall(DOC.read_text()):
        if kind == 'file':
            files[path] = body
        else:
            rows.append(body.strip())
    assert len(rows) == 1, rows
    return files, rows[0]


def table_with_row(row_text: str) -> str:
    """vendors/table.py with the row appended to ROWS."""
    text = (ROOT / 'src/stepper_drivers/stepper_drivers/vendors/table.py').read_text()
    end = text.index('\n)\n', text.index('ROWS: tuple[VendorRow, ...] = ('))
    return text[:end] + '\n    ' + row_text.replace('\n', '\n    ') + ',' + text[end:]


@pytest.fixture(scope='module')
def toy(tmp_path_factory):
    """The page's files and the row in a temporary tree shaped like the workspace."""
    tmp = tmp_path_factory.mktemp('ws')
    files, row_text = doc_blocks()
    for path, text in files.items():
        (tmp / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp / path).write_text(text)
    for package in ('stepper_drivers', 'stepper_sim'):
        (tmp / 'src' / package).mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / 'src' / package / 'setup.py', tmp / 'src' / package / 'setup.py')
    table = tmp / 'src/stepper_drivers/stepper_drivers/vendors/table.py'
    table.parent.mkdir(parents=True, exist_ok=True)
    table.write_text(table_with_row(row_text))
    return tmp, files


def test_the_walk_through_writes_the_pieces_the_table_names(toy):
    """The files of the page are exactly the pieces the row's conventions point at."""
    _tmp, files = toy
    rows = runpy.run_path(str(_tmp / 'src/stepper_drivers/stepper_drivers/vendors/table.py'))
    row = rows['BY_KEY'][KEY]
    # the vendor's package (its entry) and the simulator's
    package = 'src/stepper_drivers/' + row.module.replace('.', '/')
    sim_file = 'src/stepper_sim/' + row.simulator.split(':')[0].replace('.', '/') + '/__init__.py'
    # five files and the row: nothing else
    assert set(files) == {
        f'{package}/__init__.py', f'{package}/regmap.py', sim_file,
        f'config/{row.params_file}', f'config/{row.sim_params_file}'}
    assert [r.key for r in rows['ROWS']] == [*vendor_table.KEYS, KEY]


def console_scripts(setup_py) -> dict[str, str]:
    import setuptools
    captured = {}
    saved = setuptools.setup
    setuptools.setup = lambda **kwargs: captured.update(kwargs)
    try:
        runpy.run_path(str(setup_py))
    finally:
        setuptools.setup = saved
    return dict(line.replace(' ', '').split('=')
                for line in captured['entry_points']['console_scripts'])


def test_both_setup_py_make_the_console_scripts_from_the_row(toy):
    tmp, _files = toy
    drivers = console_scripts(tmp / 'src/stepper_drivers/setup.py')
    sims = console_scripts(tmp / 'src/stepper_sim/setup.py')
    assert drivers['toy_node'] == 'stepper_drivers.ros.entry_points:main'
    assert drivers['toy_lifecycle_node'] == 'stepper_drivers.ros.entry_points:main'
    assert sims['toy_sim'] == 'stepper_sim.toy:main'
    # and without the row, as the workspace is
    assert 'toy_node' not in console_scripts(ROOT / 'src/stepper_drivers/setup.py')


def load(name: str, path) -> object:
    package = [str(path.parent)] if path.name == '__init__.py' else None
    spec = importlib.util.spec_from_file_location(name, path, submodule_search_locations=package)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def installed(toy, monkeypatch):
    """The toy packages importable under their names, the table with the row in place of
    vendors/table.py, and the table's readers reloaded on it (and back afterwards)."""
    tmp, _files = toy
    for name in ('stepper_drivers.vendors.table', 'stepper_drivers.vendors.toy.regmap',
                 'stepper_drivers.vendors.toy', 'stepper_sim.toy'):
        monkeypatch.setitem(sys.modules, name, sys.modules.get(name))
    from stepper_drivers import vendors as vendors_package
    vendors = tmp / 'src/stepper_drivers/stepper_drivers/vendors'
    monkeypatch.setattr(vendors_package, 'table',
                        load('stepper_drivers.vendors.table', vendors / 'table.py'))
    load('stepper_drivers.vendors.toy.regmap', vendors / 'toy' / 'regmap.py')
    toy_module = load('stepper_drivers.vendors.toy', vendors / 'toy' / '__init__.py')
    import stepper_sim
    sim = load('stepper_sim.toy', tmp / 'src/stepper_sim/stepper_sim/toy/__init__.py')
    from stepper_drivers.cli import main, scan
    from stepper_drivers.ros import entry_points
    readers = [importlib.reload(m) for m in (entry_points, scan, main)]
    try:
        yield tmp, toy_module, sim, readers
    finally:
        monkeypatch.undo()
        for m in readers:
            importlib.reload(m)
        del stepper_sim


def test_the_executable_and_stepperctl_know_the_vendor(installed):
    _tmp, _toy, _sim, (entry_points, scan, main) = installed
    assert 'toy_node' in entry_points.BY_NODE                      # main() runs it by name
    assert 'toy_lifecycle_node' in entry_points.BY_LIFECYCLE_NODE
    assert scan.NODE_NAMES['toy'] == 'toy_node' and scan.ADDRESS_NAMES['toy'] == 'address'
    assert 'toy' not in scan.scanners()          # VENDOR.scanner None: no scan command
    args = main.build_parser().parse_args(['scan', 'rd4', '--port', 'x'])
    assert args.vendor == 'rd4'


def test_the_node_runs_on_the_row_with_the_vendors_rules(installed, monkeypatch):
    import rclpy
    from rclpy.parameter import Parameter
    from stepper_drivers.contract.drive import complete
    from stepper_drivers.ros.node import DriveNode
    from stepper_drivers.ros.params import ParameterError, declare_all
    tmp, toy_module, sim, _readers = installed
    config = str(tmp / 'config' / 'toy.yaml')
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')     # in no graph (see there)

    def node(*ros_args):
        args = ['toy_node', '--ros-args', '--params-file', config, *ros_args]
        rclpy.try_shutdown()
        rclpy.init(args=args)
        return DriveNode(toy_module.VENDOR, 'toy_node', lambda n: declare_all(
            n, toy_module.VENDOR, args, toy_module.validate))

    try:
        with pytest.raises(ParameterError,
                           match=r'drives.axis2.address: 1 is already used by drive axis1'):
            node('-p', 'drives.axis2.address:=1')
        n = node()
        try:
            joints = [h.cfg.joint_name for h in n.handles.values()]
            assert joints == ['toy_joint1', 'toy_joint2']
            (r,) = n.set_parameters([Parameter('drives.axis1.homing.method', value=19)])
            assert not r.successful and 'is not a Toy Step method' in r.reason, r.reason
            sim.main('toy0', (1, 2))
            drive = n.handles['axis1'].drive
            # the contract alone: no optional capability (contract/capabilities.py)
            from stepper_drivers.contract import capabilities
            optional = [c for c in vars(capabilities).values() if isinstance(c, type)
                        and c.__module__ == capabilities.__name__]
            assert len(optional) >= 8 and not any(
                isinstance(drive, c) or isinstance(drive.bus, c) for c in optional)
            assert complete(drive.connect()) == {'address': '1'}
            complete(drive.move_to(123, None))
            assert complete(drive.read_state()).position_steps == 123
        finally:
            n.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_the_generic_launch_file_starts_the_node_and_with_sim_true_the_simulator(
        installed, monkeypatch):
    """driver.launch.py vendor:=toy, as `ros2 launch` runs it (rigs_launch's model) with the
    table that has the row: the toy's executables, from the copied setup.py files (the toy is not
    installed), and its params files."""
    import rigs_launch
    tmp, _toy, _sim, _readers = installed
    config = tmp / 'config'
    for f in rigs_launch.CONFIG_DIR.glob('*.yaml'):
        shutil.copy(f, config / f.name)
    monkeypatch.setattr(rigs_launch, 'CONFIG_DIR', config)
    scripts = {p: set(console_scripts(tmp / 'src' / p / 'setup.py'))
               for p in ('stepper_drivers', 'stepper_sim')}

    def check_installed(package, executable):
        assert executable in scripts[package], f'{package} has no executable {executable}'

    monkeypatch.setattr(rigs_launch, 'check_installed', check_installed)
    monkeypatch.setattr(rigs_launch, 'INSTALL', tmp / 'no-install')  # config files: from the tree
    (tmp / 'no-install/stepper_drivers/share/stepper_drivers/config').mkdir(parents=True)
    for f in config.glob('*.yaml'):
        shutil.copy(f, tmp / 'no-install/stepper_drivers/share/stepper_drivers/config' / f.name)
    launch = rigs_launch.ros2_launch
    assert launch('driver.launch.py', vendor='toy') == {'toy_node': ['config/toy.yaml']}
    assert launch('driver.launch.py', vendor='toy', sim='true') == {
        'toy_sim': ['config/toy_sim.yaml'], 'toy_node': ['config/toy.yaml']}
    assert launch('driver.launch.py', vendor='toy', lifecycle='true') == {
        'toy_lifecycle_node': ['config/toy.yaml']}
    # the demo takes the row too
    started = launch('demo.launch.py')
    assert started['toy_node'] == ['config/toy.yaml'] and 'rd4_node' in started
    node_p, sim_p = (next(iter(yaml.safe_load((config / n).read_text()).values()))
                     ['ros__parameters'] for n in ('toy.yaml', 'toy_sim.yaml'))
    assert node_p['port'] == sim_p['port']
