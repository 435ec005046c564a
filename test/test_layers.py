"""The import graph runs only downwards, and the folders are the layers.

stepper_drivers, bottom to top (each folder imports only the folders listed under it):

    contract/    Bus, Drive, DriveState, errors, units, parameter and scanner contracts
    protocol/    frames and transports (every drive.Bus lives here)        -> contract
    profiles/    device profiles (CiA 402: tables, walker, modes, drive)   -> protocol, contract
    vendors/     one package per vendor (entry, map, scanner) + the table  -> profiles, protocol,
                                                                              contract
    owner/       the bus owner: one thread per bus, its order rules        -> contract
    motion/      trajectories and their follower                           -> owner, contract
    cli/         stepperctl                                                -> vendors, contract
    ros/         the node, its services, publishing, trajectory interface  -> all but cli

contract/ to motion/ import no ROS. A vendor package uses only itself among the vendors; its
map (`regmap`) uses protocol/ only; its scanner (`scan`) uses contract/, protocol/ and its map,
never its vendor entry, which imports it, nor cli/. The table (vendors/table.py) is plain data.

stepper_sim: core/ (axis, motion, lines, faults, the broker, the sim's ROS node), cia402/ (the
simulated CiA 402 slave) -> core/, one package per vendor -> cia402/, core/; harness.py starts
processes for tests and benchmarks. A simulator shares protocol codecs (not transports) and its
own vendor's map with the driver, never a drive class, profiles/, the owner or the node.

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
# what each top folder of stepper_drivers may import from the package, besides itself
LAYERS = {
    'contract': (),
    'protocol': ('contract',),
    'profiles': ('contract', 'protocol'),
    'vendors': ('contract', 'protocol', 'profiles'),
    'owner': ('contract',),
    'motion': ('contract', 'owner'),
    'cli': ('contract', 'vendors'),
    'ros': ('contract', 'protocol', 'profiles', 'vendors', 'owner', 'motion'),
}
ROS_FREE = ('contract', 'protocol', 'profiles', 'vendors', 'owner', 'motion')
# what each top folder of stepper_sim may import from stepper_sim, besides itself
SIM_LAYERS = {'core': (), 'cia402': ('core',)}
SIM_VENDOR = ('core', 'cia402')
# protocol modules that are transports (a bus, a line): the simulators do not use them
# (modbus_rtu holds the RTU frame codec the RD4 simulator answers with, beside its bus)
TRANSPORTS = ('canopen_link', 'canopen_remote', 'canopen_producers', 'xmind_k_bus', 'ascii_line',
              'modbus_tcp')


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


def top(name: str) -> str:
    """'stepper_drivers.protocol.modbus_rtu.ModbusRtuBus' -> 'protocol'."""
    parts = name.split('.')
    return parts[1] if len(parts) > 1 else ''


def vendor_part(name: str) -> tuple[str, str]:
    """'stepper_drivers.vendors.rd4.scan.RD4_SCANNER' -> ('rd4', 'scan'); the vendor entry
    (the package itself) -> ('rd4', ''); vendors/table -> ('table', '')."""
    parts = name.split('.')[2:]
    key = parts[0] if parts else ''
    sub = parts[1] if len(parts) > 1 and parts[1] in ('regmap', 'scan', 'drive') else ''
    return key, sub


def problems(module: str, imported: set[str]) -> list[str]:
    """What `module` may not import, one line each."""
    out = []
    ours = {n for n in imported if within(n, 'stepper_drivers')}
    ros = sorted(n for n in imported if is_ros(n))
    sim = sorted(n for n in imported if within(n, 'stepper_sim'))

    def bad(what, names):
        out.extend(f'{module} imports {n} ({what})' for n in sorted(names))

    if within(module, 'stepper_drivers'):
        layer = top(module)
        bad('the product does not import the simulators', sim)
        if layer in ROS_FREE:
            bad(f'{layer}/ imports no ROS', ros)
        if layer in LAYERS:
            allowed = (layer, *LAYERS[layer])
            bad(f'{layer}/ uses only {", ".join(f"{a}/" for a in allowed)}',
                {n for n in ours if top(n) not in allowed})
        if layer == 'vendors':
            key, sub = vendor_part(module)
            mine = {n for n in ours if top(n) == 'vendors'}
            if key == 'table':
                bad('the vendor table is plain data', ours)
            bad('a vendor package uses no other vendor', {
                n for n in mine if vendor_part(n)[0] != key})
            if sub == 'regmap':
                bad('a map uses only protocol/ (codecs, CiA numbers)',
                    {n for n in ours if top(n) != 'protocol'})
            elif sub == 'scan':
                bad('a scanner uses contract/, protocol/ and its map only', {
                    n for n in ours if top(n) not in ('contract', 'protocol')
                    and vendor_part(n) != (key, 'regmap')})
    elif module == 'stepper_sim.harness':
        pass   # test and benchmark infrastructure, not a simulator
    elif within(module, 'stepper_sim'):
        layer = top(module)
        mine = {n for n in imported if within(n, 'stepper_sim') and top(n) != layer}
        allowed = SIM_LAYERS.get(layer, SIM_VENDOR)
        bad(f'stepper_sim {layer}/ uses only {", ".join(f"{a}/" for a in allowed) or "itself"}',
            {n for n in mine if top(n) not in allowed})
        shared = {n for n in ours if (top(n) == 'protocol' and n.split('.')[2] not in TRANSPORTS)
                  or (top(n) == 'vendors' and vendor_part(n) == (layer, 'regmap'))}
        # the sims' ROS node reads its params file the way the nodes do (no drive logic)
        if module == 'stepper_sim.core.sim_node':
            shared |= {n for n in ours if within(n, 'stepper_drivers.ros.params')}
        bad('a simulator uses protocol codecs and its own vendor map only', ours - shared)
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
        if within(module, 'stepper_drivers.protocol', 'stepper_drivers.contract.drive'):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and any(
                    ast.unparse(b) in ('Bus', 'drive.Bus') for b in node.bases):
                out.append(f'{module}.{node.name} is a transport (drive.Bus) outside protocol/')
    return out


def violations() -> list[str]:
    return [p for module, imported in modules() for p in problems(module, imported)] \
        + misplaced_transports()


def import_cycles(graph_of: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other round in a circle (strongly connected
    components of the import graph; `graph_of`: module -> what it imports, as `imports` reads
    it, lazy and type-only imports counted), largest first."""

    def module_of(name: str) -> str:
        while name and name not in graph_of:
            name = name.rpartition('.')[0]
        return name
    graph = {m: {module_of(n) for n in imported} - {m, ''} for m, imported in graph_of.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v: str) -> None:                       # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1:
                cycles.append(sorted(group))
    for v in graph:
        if v not in index:
            visit(v)
    return sorted(cycles, key=len, reverse=True)


def test_no_module_imports_itself_round_a_circle():
    """Every import arrow points one way: no group of modules imports each other in a circle,
    not even lazily (inside a function) or for types only (under TYPE_CHECKING); a module that
    needs something of the one above it says what in a Protocol of its own."""
    found = import_cycles(dict(modules()))
    assert not found, '\n'.join(' -> '.join(c) for c in found)


def test_a_circle_through_a_lazy_and_a_type_only_import_is_found(tmp_path):
    package = tmp_path / 'stepper_drivers'
    (package / 'motion').mkdir(parents=True)
    files = {'a': 'def f():\n    from .b import B\n',
             'b': 'from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import A\n',
             'c': 'from .a import f\n'}
    graph = {}
    for name, text in files.items():
        (package / 'motion' / f'{name}.py').write_text(text)
        graph[f'stepper_drivers.motion.{name}'] = imports(package / 'motion' / f'{name}.py',
                                                          package)
    assert import_cycles(graph) == [['stepper_drivers.motion.a', 'stepper_drivers.motion.b']]
    del graph['stepper_drivers.motion.b']
    assert import_cycles(graph) == []


MODULE_MAX_LINES = 600
CLASS_MAX_LINES = 400
# A class or module may be longer where its docstring says why, in a sentence with this phrase.
LONGER_BECAUSE = 'is longer than the limit because'


def oversized() -> list[str]:
    out = []
    for package_dir in (DRIVERS, SIM):
        for path in sorted(package_dir.rglob('*.py')):
            text = path.read_text()
            tree = ast.parse(text)
            lines = text.count('\n')
            if lines > MODULE_MAX_LINES and LONGER_BECAUSE not in (ast.get_docstring(tree) or ''):
                out.append(f'{path.relative_to(ROOT)}: {lines} lines')
            for node in ast.walk(tree):
                if isinstance(node, ast.ClassDef):
                    size = node.end_lineno - node.lineno + 1
                    if size > CLASS_MAX_LINES and \
                            LONGER_BECAUSE not in (ast.get_docstring(node) or ''):
                        out.append(f'{path.relative_to(ROOT)}: class {node.name} {size} lines')
    return out


def test_no_module_over_600_lines_and_no_class_over_400_unless_it_says_why():
    found = oversized()
    assert not found, '\n'.join(found)


def test_every_class_name_is_unique_across_both_packages():
    """One name, one thing (the README's glossary): no two classes of stepper_drivers and
    stepper_sim share a name (there were two Job, two Segment)."""
    where: dict[str, list[str]] = {}
    for package_dir in (DRIVERS, SIM):
        for path in sorted(package_dir.rglob('*.py')):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef):
                    where.setdefault(node.name, []).append(module_name(path, package_dir))
    twice = {name: places for name, places in where.items() if len(places) > 1}
    assert not twice, twice


def test_the_import_graph_runs_only_downwards():
    found = violations()
    assert not found, '\n'.join(found)


@pytest.mark.parametrize('module, imported, words', [
    ('stepper_drivers.protocol.canopen_link', {'stepper_drivers.vendors.vector_step.regmap'},
     'protocol/ uses only'),
    ('stepper_drivers.protocol.modbus', {'rclpy.node.Node'}, 'protocol/ imports no ROS'),
    ('stepper_drivers.contract.drive', {'stepper_drivers.owner.commands.Command'},
     'contract/ uses only'),
    ('stepper_drivers.profiles.cia402.drive', {'stepper_drivers.vendors.xplus_mt'},
     'profiles/ uses only'),
    ('stepper_drivers.vendors.vector_step.regmap',
     {'ament_index_python.packages.get_package_share_directory'}, 'vendors/ imports no ROS'),
    ('stepper_drivers.vendors.xmind_k', {'stepper_drivers.ros.node.DriveNode'},
     'vendors/ uses only'),
    ('stepper_drivers.vendors.xmind_k', {'stepper_drivers.vendors.rd4.regmap'},
     'a vendor package uses no other vendor'),
    ('stepper_drivers.vendors.table', {'stepper_drivers.contract.drive.Vendor'},
     'the vendor table is plain data'),
    ('stepper_drivers.vendors.rd4.regmap', {'stepper_drivers.profiles.cia402.state_machine'},
     'a map uses only'),
    ('stepper_drivers.vendors.rd4.scan', {'stepper_drivers.vendors.rd4.VENDOR'},
     'a scanner uses'),
    ('stepper_drivers.vendors.vector_step.scan', {'rclpy.node.Node'}, 'vendors/ imports no ROS'),
    ('stepper_drivers.contract.scanning', {'rclpy.logging'}, 'contract/ imports no ROS'),
    ('stepper_drivers.owner', {'stepper_drivers.vendors.rd4'}, 'owner/ uses only'),
    ('stepper_drivers.owner.schedule', {'stepper_drivers.motion.follow.Follower'},
     'owner/ uses only'),
    ('stepper_drivers.motion.follow', {'stepper_drivers.ros.node.DriveNode'},
     'motion/ uses only'),
    ('stepper_drivers.cli.scan', {'stepper_drivers.ros.node.DriveNode'}, 'cli/ uses only'),
    ('stepper_drivers.cli.scan', {'stepper_sim.core.socketcand_broker.SocketcandBroker'},
     'the product does not import the simulators'),
    ('stepper_sim.vector_step.sim', {'stepper_drivers.vendors.vector_step.VectorStepDrive'},
     'a simulator uses'),
    ('stepper_sim.vector_step.sim', {'stepper_drivers.protocol.canopen_link.CanBus'},
     'a simulator uses'),
    ('stepper_sim.xplus_mt.sim', {'stepper_drivers.vendors.rd4.regmap.REGISTERS'},
     'a simulator uses'),
    ('stepper_sim.rd4.sim', {'stepper_drivers.profiles.cia402.state_machine'},
     'a simulator uses'),
    ('stepper_sim.core.axis', {'stepper_sim.cia402.slave.PowerStateMachine'},
     'stepper_sim core/ uses only itself'),
    ('stepper_sim.rd4.sim', {'stepper_sim.xmind_k.sim.XmindKLine'},
     'stepper_sim rd4/ uses only'),
])
def test_each_rule_refuses_an_upward_import(module, imported, words):
    found = problems(module, imported)
    assert len(found) == 1 and words in found[0], found


def test_every_scanner_is_a_vendor_scan_module_the_rules_read():
    """A vendor's VENDOR.scanner lives in vendors/<key>/scan.py (the rule for scanners reads
    that name), and the graph above reads it and contract/scanning.py."""
    import importlib

    from stepper_drivers.vendors import table as vendor_table

    read = {name for name, _imported in modules()}
    assert 'stepper_drivers.contract.scanning' in read
    for row in vendor_table.ROWS:
        scanner = importlib.import_module(row.module).VENDOR.scanner
        if scanner is None:
            continue
        module = f'stepper_drivers.vendors.{row.key}.scan'
        assert module in read, module
        assert scanner.scan.__module__ == scanner.add_options.__module__ == module, row.key


def test_relative_imports_resolve_to_the_module_they_name(tmp_path):
    package = tmp_path / 'stepper_drivers'
    (package / 'protocol').mkdir(parents=True)
    path = package / 'protocol' / 'x.py'
    path.write_text('from ..vendors.vector_step import regmap as vm\nfrom . import cia301\n'
                    'def f():\n    from ..ros import node\n')
    assert imports(path, package) == {'stepper_drivers.vendors.vector_step.regmap',
                                      'stepper_drivers.protocol.cia301',
                                      'stepper_drivers.ros.node'}


def test_the_node_layer_finds_the_installed_eds_the_vendor_names():
    """vendors/vector_step names its EDS relative to the share directory (no ROS there);
    ros/entry_points.share_files resolves it through ament's package index."""
    from stepper_drivers.ros.entry_points import share_files
    from stepper_drivers.ros.params import BusConfig
    from stepper_drivers.vendors import vector_step

    files = vector_step.VENDOR.share_files
    cfg = share_files(BusConfig({'can.eds_file': ''}, []), files)
    path = pathlib.Path(cfg.params['can.eds_file'])
    assert path.match('share/stepper_drivers/config/vector_step.eds'), path
    assert path.read_bytes() == (ROOT / 'config' / 'vector_step.eds').read_bytes()
    given = share_files(BusConfig({'can.eds_file': '/cell/drive.eds'}, []), files)
    assert given.params['can.eds_file'] == '/cell/drive.eds'      # a given file is kept
