"""docs/interface.md matches what the nodes declare: topics, services, actions and parameters.

Each vendor's DriveNode is built in this process (one drive, nothing opened or spun: the
constructor declares every parameter and creates every interface), then:
- the interface table's (name, type) rows must equal what the node's own graph shows;
- the parameter tables between `<!-- BEGIN generated: X -->` and `<!-- END generated: X -->` must
  equal what this file renders from the declarations (name, type, default, range, unit,
  runtime-changeable, description).
After changing a parameter, regenerate the tables:  python test/test_interface_docs.py --write
"""

from __future__ import annotations

import importlib
import math
import pathlib
import re
import sys

import pytest
from stepper_drivers.vendors.table import BY_KEY, KEYS

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOC = ROOT / 'docs' / 'interface.md'
VENDORS = KEYS
DRIVE = 'axis1'
# rclpy's own per-node interfaces, not part of our contract
STANDARD = re.compile(r'/(describe_parameters|get_parameters|get_parameter_types|list_parameters|'
                      r'set_parameters|set_parameters_atomically|get_type_description)$')
IGNORED_TOPICS = ('/rosout', '/parameter_events')
TYPE_NAMES = {bool: 'bool', int: 'integer', float: 'double', str: 'string', list: 'string[]'}


# ------------------------------------------------------------------------------ declarations
def build_nodes() -> dict:
    """{vendor: (interfaces, params)} from a DriveNode per vendor in this process (the node
    layer uses rclpy's default context: nothing else in the test process does)."""
    import rclpy
    from stepper_drivers.ros.node import DriveNode
    from stepper_drivers.ros.params import declare_all

    out = {}
    args = ['doc', '--ros-args', '-p', f'drives:=[{DRIVE}]']
    rclpy.init(args=args)
    try:
        for v in VENDORS:
            module = importlib.import_module(BY_KEY[v].module)
            vendor = module.VENDOR
            node = DriveNode(vendor, f'{v}_node', lambda n, m=module: declare_all(
                n, m.VENDOR, args, m.validate))
            try:
                out[v] = (interfaces(node, f'{v}_node'), params(node, vendor))
            finally:
                node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return out


def _relative(name: str, node_name: str) -> str:
    prefix = f'/{node_name}/'
    if name.startswith(prefix + DRIVE + '/'):
        return '~/<drive>/' + name[len(prefix + DRIVE + '/'):]
    if name.startswith(prefix):
        return '~/' + name[len(prefix):]
    return name


def interfaces(node, node_name: str) -> set[tuple[str, str, str]]:
    """(kind, name, type): kind in topic-out, topic-in, service, action."""
    found = set()
    for name, types in node.get_publisher_names_and_types_by_node(node_name, '/'):
        if name not in IGNORED_TOPICS and '/_action/' not in name:
            found.add(('out', _relative(name, node_name), types[0]))
    for owner in (node_name, f'_{node_name}_commands'):     # the command topics' own node
        for name, types in node.get_subscriber_names_and_types_by_node(owner, '/'):
            if '/_action/' not in name:
                found.add(('in', _relative(name, node_name), types[0]))
    for name, types in node.get_service_names_and_types_by_node(node_name, '/'):
        if STANDARD.search(name):
            continue
        if name.endswith('/_action/send_goal'):
            action_type = types[0].replace('_SendGoal', '')
            found.add(('action', _relative(name[:-len('/_action/send_goal')], node_name),
                       action_type))
        elif '/_action/' not in name:
            found.add(('service', _relative(name, node_name), types[0]))
    return found


def params(node, vendor) -> dict[str, dict]:
    """Declared parameters by name (drives.<drive>. for per-drive ones), with their metadata."""
    from stepper_drivers.ros.params import BUS_PARAMS, DRIVE_PARAMS
    specs = {p.name: p for p in (*BUS_PARAMS, *vendor.params)
             if getattr(p, 'scope', 'bus') == 'bus'}
    specs.update({f'drives.<drive>.{p.name}': p for p in DRIVE_PARAMS})
    specs.update({f'drives.<drive>.{p.name}': p for p in vendor.params if p.scope == 'drive'})
    out = {}
    for name, param in node._parameters.items():
        if name in ('use_sim_time', 'start_type_description_service'):
            continue
        key = name.replace(f'drives.{DRIVE}.', 'drives.<drive>.').replace(
            f'constraints.{DRIVE}.', 'constraints.<joint>.')     # the drive's joint name
        d = node.describe_parameter(name)
        spec = specs.get(key)
        if key == 'drives':
            value = []
        else:
            value = param.value
        out[key] = dict(value=value, read_only=d.read_only, description=d.description,
                        spec=spec, vendor=spec is not None and spec in vendor.params)
    return out


# --------------------------------------------------------------------------------- rendering
def _unit(name: str, description: str) -> str:
    m = re.search(r'\[([^\]]+)\]\s*$', description)
    if m:
        return m.group(1)
    for suffix, unit in (('_s', 's'), ('_ms', 'ms'), ('_hz', 'Hz'), ('_m', 'm')):
        if name.endswith(suffix):
            return unit
    return ''


def _fmt(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        if math.isinf(value):
            return '-inf' if value < 0 else 'inf'
        return f'{value:g}'
    if isinstance(value, str):
        return f"'{value}'"
    if isinstance(value, list):
        return '[' + ', '.join(str(v) for v in value) + ']'
    return str(value)


def _range(spec) -> str:
    if spec is None:
        return ''
    if spec.choices:
        return ', '.join(f"'{c}'" if c == '' else c for c in spec.choices)
    lo, hi = spec.min_value, spec.max_value
    if lo is None and hi is None:
        return ''
    return f'{_fmt(lo) if lo is not None else "-inf"} .. {_fmt(hi) if hi is not None else "inf"}'


def _row(name: str, p: dict, default=None) -> str:
    value = p['value'] if default is None else default
    desc = re.sub(r'\s*\[[^\]]+\]\s*$', '', p['description']).replace('|', '\\|')
    return (f"| `{name}` | {TYPE_NAMES[type(value)]} | `{_fmt(value)}` | {_range(p['spec'])} | "
            f"{_unit(name, p['description'])} | {'' if p['read_only'] else 'yes'} | {desc} |")


HEAD = ('| name | type | default | range / allowed | unit | runtime | description |\n'
        '|---|---|---|---|---|---|---|')


def render(nodes: dict) -> dict[str, str]:
    """The generated blocks by marker name."""
    from stepper_drivers.ros.params import BUS_PARAMS, DRIVE_PARAMS
    first = nodes[VENDORS[0]][1]
    blocks = {}
    common_bus = [p.name for p in BUS_PARAMS] + ['drives']
    blocks['common-bus'] = '\n'.join([HEAD] + [_row(n, first[n]) for n in common_bus])
    common_drive = [f'drives.<drive>.{p.name}' for p in DRIVE_PARAMS]
    blocks['common-drive'] = '\n'.join(
        [HEAD] + [_row(n, first[n], DRIVE_PARAMS[i].default) for i, n in enumerate(common_drive)])
    for v in VENDORS:
        _ifaces, ps = nodes[v]
        vendor = importlib.import_module(BY_KEY[v].module).VENDOR
        rows = [_row(n, p) for n, p in ps.items() if p['vendor']]
        lines = [HEAD] + rows
        differ = [(n, ps[n]['value'], DRIVE_PARAMS[i].default)
                  for i, n in enumerate(common_drive) if ps[n]['value'] != DRIVE_PARAMS[i].default]
        if differ:
            lines.append('')
            lines.append('Common drive parameters with another default on this node: '
                         + ', '.join(f'`{n.split(".", 2)[2]}` = `{_fmt(val)}`'
                                     for n, val, _d in differ) + '.')
        assert set(vendor.drive_defaults) >= {n.split('.', 2)[2] for n, _v, _d in differ}
        blocks[f'vendor-{v}'] = '\n'.join(lines)
    return blocks


MARKER = re.compile(r'<!-- BEGIN generated: (?P<name>[\w-]+) -->\n(?P<body>.*?)'
                    r'<!-- END generated: (?P=name) -->', re.S)


def doc_blocks(text: str) -> dict[str, str]:
    return {m.group('name'): m.group('body').rstrip('\n') for m in MARKER.finditer(text)}


def write_doc(blocks: dict[str, str]) -> None:
    text = DOC.read_text()

    def sub(m):
        name = m.group('name')
        return (f'<!-- BEGIN generated: {name} -->\n{blocks[name]}\n'
                f'<!-- END generated: {name} -->')
    DOC.write_text(MARKER.sub(sub, text))


def doc_interfaces(text: str) -> set[tuple[str, str, str]]:
    """(direction/kind, name, type) rows of the interface table."""
    rows = set()
    for m in re.finditer(r'^\| `([^`]+)` \| `([^`]+)` \| (out|in|service|action) \|', text,
                         re.M):
        name, typ, kind = m.groups()
        rows.add((kind, name, typ))
    return rows


# ------------------------------------------------------------------------------------- tests
@pytest.fixture(scope='module')
def nodes():
    return build_nodes()


def test_every_vendor_offers_the_same_interface(nodes):
    first = nodes[VENDORS[0]][0]
    for v in VENDORS[1:]:
        assert nodes[v][0] == first, f'{v} differs: {nodes[v][0] ^ first}'


def test_interface_table_matches_the_nodes(nodes):
    documented = doc_interfaces(DOC.read_text())
    actual = nodes[VENDORS[0]][0]
    assert documented == actual, (f'missing in docs/interface.md: {sorted(actual - documented)}; '
                                  f'documented but not offered: {sorted(documented - actual)}')


def test_parameter_tables_match_the_declarations(nodes):
    blocks = render(nodes)
    documented = doc_blocks(DOC.read_text())
    assert set(documented) == set(blocks), f'markers: {sorted(documented)} vs {sorted(blocks)}'
    for name, body in blocks.items():
        assert documented[name] == body, (f'docs/interface.md block {name!r} is out of date: '
                                          'run  python test/test_interface_docs.py --write')


def test_every_declared_parameter_is_documented(nodes):
    text = DOC.read_text()
    for v in VENDORS:
        for name in nodes[v][1]:
            assert f'`{name}`' in text, f'{v}: parameter {name} not in docs/interface.md'


def test_a_changed_declaration_is_detected(nodes):
    """The comparison can fail: a different default renders a different table."""
    blocks = render(nodes)
    import copy
    changed = copy.deepcopy(nodes)
    changed['xplus_mt'][1]['timeout_s']['value'] = 0.25
    assert render(changed)['common-bus'] != blocks['common-bus']


if __name__ == '__main__':
    if '--write' in sys.argv:
        write_doc(render(build_nodes()))
        print(f'updated {DOC}')
    else:
        print(__doc__)
