"""The import graph runs only downwards.

    protocol/  ->  vendors/  ->  supervisor / node / cli / entry points
    (drive.py, the Bus/Drive contract, and the ROS-free helpers sit under all of them;
    every transport, a drive.Bus, lives in protocol/; a vendor's bus scanner, vendors/*_scan,
    uses the scanning helpers and its map, never its vendor module, which imports it, nor cli/)
    stepper_sim -> protocol codecs and vendors/*_map only (never a drive class, cia402.py, the
    supervisor or the node: a simulator shares codecs and maps with the driver, not its logic)

Every module's imports are read with `ast` (a lazy import inside a function counts as much as
one at the top) and resolved to dotted names; each rule below names what a layer may use.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DRIVERS = ROOT / 'src' / 'stepper_drivers' / 'stepper_drivers'
SIM = ROOT / 'src' / 'stepper_sim' / 'stepper_sim'

ROS = ('rclpy', 'ament_index_python', 'rcl_interfaces', 'launch', 'launch_ros',
       'rosidl_runtime_py')
# ROS-free modules under the vendors: the contract, CiA 402, units, rules, planning, supervisor,
# what the bus scanners share
CORE = ('drive', 'cia402', 'cia402_drive', 'cia402_modes', 'units', 'param_rules', 'trajectory',
        'commands', 'supervisor', 'poll_group', 'follow', 'scanning')
# protocol modules that are transports (a bus, a line): the simulators do not use them
TRANSPORTS = ('canopen_link', 'xmind_k_bus', 'ascii_line', 'modbus_tcp')


def module_name(path: pathlib.Path, package_dir: pathlib.Path) -> str:
    parts = list(path.relative_to(package_dir.parent).with_suffix('').parts)
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def imports(path: pathlib.Path, package_dir: pathlib.Path) -> set[str]:
    """Dotted names of everything the module imports ('from a import b' gives a.b: b may be a
    module; a name from a module still names that module as its prefix)."""
    name = module_name(path, package_dir)
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - node.level + 1]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            if module == '__future__':
                continue
            found.update(f'{module}.{alias.name}' for alias in node.names)
    return found


def is_ros(name: str) -> bool:
    top = name.split('.')[0]
    return top in ROS or top.endswith('_msgs')


def within(name: str, *prefixes: str) -> bool:
    return any(name == p or name.startswith(p + '.') for p in prefixes)


def drivers_module(name: str) -> str:
    """'stepper_drivers.protocol.modbus_rtu.ModbusRtuBus' -> 'protocol.modbus_rtu'."""
    parts = name.split('.')[1:]
    if parts and parts[0] in ('protocol', 'vendors', 'cli'):
        return '.'.join(parts[:2])
    return parts[0] if parts else ''


def problems(module: str, imported: set[str]) -> list[str]:
    """What `module` may not import, one line each."""
    out = []
    ours = {drivers_module(n) for n in imported if within(n, 'stepper_drivers')}
    ros = sorted(n for n in imported if is_ros(n))
    sim = sorted(n for n in imported if within(n, 'stepper_sim'))

    def bad(what, names):
        out.extend(f'{module} imports {n} ({what})' for n in sorted(names))

    if within(module, 'stepper_drivers.protocol'):
        bad('protocol/ uses only protocol/ and drive.py',
            {m for m in ours if not (m == 'drive' or m.startswith('protocol'))})
        bad('protocol/ imports no ROS', ros)
        bad('the product does not import the simulators', sim)
    elif within(module, 'stepper_drivers.vendors'):
        if module.endswith('_map'):
            bad('a map uses only protocol/ (codecs, CiA numbers)',
                {m for m in ours if not m.startswith('protocol')})
        elif module.endswith('_scan'):
            bad('a scanner uses protocol/, vendors/*_map and the ROS-free core only',
                {m for m in ours if not (m in CORE or m.startswith('protocol')
                                         or (m.startswith('vendors.') and m.endswith('_map')))})
        else:
            bad('a vendor uses protocol/, vendors/ and the ROS-free core only',
                {m for m in ours if not (m in CORE or m.startswith(('protocol', 'vendors')))})
        bad('vendors/ import no ROS (the node layer resolves what needs ROS)', ros)
        bad('the product does not import the simulators', sim)
    elif (module.split('.')[-1] in CORE and module.count('.') == 1) \
            or within(module, 'stepper_drivers.supervisor'):
        bad('the core uses only the core',
            {m for m in ours if m not in CORE})
        bad('the core imports no ROS', ros)
        bad('the product does not import the simulators', sim)
    elif within(module, 'stepper_drivers'):
        bad('the product does not import the simulators', sim)
    elif module in ('stepper_sim.harness', 'stepper_sim.socketcand_broker'):
        pass   # test infrastructure, not a simulator
    elif within(module, 'stepper_sim'):
        allowed = {m for m in ours if (m.startswith('protocol.')
                                       and m.split('.')[1] not in TRANSPORTS)
                   or (m.startswith('vendors.') and m.endswith('_map'))}
        # the sims' ROS layer reads its params file the way the nodes do (no drive logic)
        if module == 'stepper_sim.sim_node':
            allowed.add('params')
        bad('a simulator uses protocol codecs and vendors/*_map only', ours - allowed)
    return out


def modules():
    for package_dir in (DRIVERS, SIM):
        for path in sorted(package_dir.rglob('*.py')):
            yield module_name(path, package_dir), imports(path, package_dir)


def misplaced_transports() -> list[str]:
    """A transport (a subclass of drive.Bus) defined outside protocol/."""
    out = []
    for path in sorted(DRIVERS.rglob('*.py')):
        module = module_name(path, DRIVERS)
        if within(module, 'stepper_drivers.protocol') or module == 'stepper_drivers.drive':
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and any(
                    ast.unparse(b) in ('Bus', 'drive.Bus') for b in node.bases):
                out.append(f'{module}.{node.name} is a transport (drive.Bus) outside protocol/')
    return out


def violations() -> list[str]:
    return [p for module, imported in modules() for p in problems(module, imported)] \
        + misplaced_transports()


def test_the_import_graph_runs_only_downwards():
    found = violations()
    assert not found, '\n'.join(found)


@pytest.mark.parametrize('module, imported, words', [
    ('stepper_drivers.protocol.canopen_link', {'stepper_drivers.vendors.vector_step_map'},
     'protocol/ uses only'),
    ('stepper_drivers.protocol.modbus', {'rclpy.node.Node'}, 'protocol/ imports no ROS'),
    ('stepper_drivers.vendors.vector_step_map',
     {'ament_index_python.packages.get_package_share_directory'}, 'vendors/ import no ROS'),
    ('stepper_drivers.vendors.xmind_k', {'stepper_drivers.node.DriveNode'}, 'a vendor uses'),
    ('stepper_drivers.vendors.rd4_map', {'stepper_drivers.cia402'}, 'a map uses only'),
    ('stepper_drivers.vendors.rd4_scan', {'stepper_drivers.cli.errors.CliError'},
     'a scanner uses'),
    ('stepper_drivers.vendors.rd4_scan', {'stepper_drivers.vendors.rd4.VENDOR'},
     'a scanner uses'),
    ('stepper_drivers.vendors.vector_step_scan', {'rclpy.node.Node'}, 'vendors/ import no ROS'),
    ('stepper_drivers.scanning', {'stepper_drivers.cli.errors.CliError'}, 'the core uses only'),
    ('stepper_drivers.scanning', {'rclpy.logging'}, 'the core imports no ROS'),
    ('stepper_drivers.supervisor', {'stepper_drivers.vendors.rd4'}, 'the core uses only'),
    ('stepper_drivers.cli.scan', {'stepper_sim.socketcand_broker.SocketcandBroker'},
     'the product does not import the simulators'),
    ('stepper_sim.vector_step_sim', {'stepper_drivers.vendors.vector_step.VectorStepDrive'},
     'a simulator uses'),
    ('stepper_sim.vector_step_sim', {'stepper_drivers.protocol.canopen_link.CanBus'},
     'a simulator uses'),
    ('stepper_sim.rd4_sim', {'stepper_drivers.cia402'}, 'a simulator uses'),
])
def test_each_rule_refuses_an_upward_import(module, imported, words):
    found = problems(module, imported)
    assert len(found) == 1 and words in found[0], found


def test_every_scanner_is_a_vendor_scan_module_the_rules_read():
    """A vendor's VENDOR.scanner lives in vendors/<key>_scan.py (the rule for scanners reads
    that name), and the graph above reads it and scanning.py."""
    import importlib

    from stepper_drivers import vendor_table

    read = {name for name, _imported in modules()}
    assert 'stepper_drivers.scanning' in read
    for row in vendor_table.ROWS:
        scanner = importlib.import_module(row.module).VENDOR.scanner
        if scanner is None:
            continue
        module = f'stepper_drivers.vendors.{row.key}_scan'
        assert module in read, module
        assert scanner.scan.__module__ == scanner.add_options.__module__ == module, row.key


def test_relative_imports_resolve_to_the_module_they_name(tmp_path):
    package = tmp_path / 'stepper_drivers'
    (package / 'protocol').mkdir(parents=True)
    path = package / 'protocol' / 'x.py'
    path.write_text('from ..vendors import vector_step_map as vm\nfrom . import cia301\n'
                    'def f():\n    from .. import node\n')
    assert imports(path, package) == {'stepper_drivers.vendors.vector_step_map',
                                      'stepper_drivers.protocol.cia301', 'stepper_drivers.node'}


def test_the_node_layer_finds_the_installed_eds_the_vendor_names():
    """vendors/vector_step.py names its EDS relative to the share directory (no ROS there);
    entry_points.share_files (the node layer) resolves it through ament's package index."""
    from stepper_drivers.entry_points import share_files
    from stepper_drivers.params import BusConfig
    from stepper_drivers.vendors import vector_step

    files = vector_step.VENDOR.share_files
    cfg = share_files(BusConfig({'can.eds_file': ''}, []), files)
    path = pathlib.Path(cfg.params['can.eds_file'])
    assert path.match('share/stepper_drivers/config/vector_step.eds'), path
    assert path.read_bytes() == (ROOT / 'config' / 'vector_step.eds').read_bytes()
    given = share_files(BusConfig({'can.eds_file': '/cell/drive.eds'}, []), files)
    assert given.params['can.eds_file'] == '/cell/drive.eds'      # a given file is kept
