"""Who may command a drive (docs/security.md): the shipped params files refuse raw register
writes, a node asked for SROS2 where the middleware cannot provide it ends at start-up with
one line and exit code 2 instead of running unsecured or failing inside the rmw, and the page's
SROS2 policy and commands are what the sros2 tools take and the node they secure."""

import pathlib
import re
import xml.etree.ElementTree as ET

import pytest
from rosharness import CONFIG, ROOT, DriveBench, executable, free_port
from stepper_drivers.ros import dds_security
from stepper_drivers.ros.params import DRIVE_PARAMS
from stepper_drivers.vendors.table import KEYS
import yaml

EXIT_TIMEOUT_S = 20.0


def raw_write_settings(tree, path=()):
    """(dotted path, value) of every allow_raw_write in a parsed params file."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from raw_write_settings(value, (*path, str(key)))
    elif path and path[-1].split('.')[-1] == 'allow_raw_write':
        yield '.'.join(path), tree


def test_no_shipped_params_file_allows_raw_writes():
    files = sorted(CONFIG.rglob('*.yaml'))
    assert {f'{v}.yaml' for v in KEYS} <= {f.name for f in files}
    allowed = [(f.name, name) for f in files
               for name, value in raw_write_settings(yaml.safe_load(f.read_text()))
               if value is not False]
    assert not allowed, f'allow_raw_write not false in {allowed}'
    # a drive without the parameter gets the declared default: refused as well
    (default,) = [p.default for p in DRIVE_PARAMS if p.name == 'allow_raw_write']
    assert default is False


class ShippedParams(DriveBench):
    """X-PLUS MT simulator and node with config/xplus_mt.yaml as shipped (a free port only)."""

    vendor = 'xplus_mt'

    def __init__(self, procs, ros):
        self.port = free_port()
        super().__init__(procs, ros)

    def link_args(self):
        return ['-p', f'port:={self.port}']


def test_a_node_with_the_shipped_params_refuses_write_register(procs, ros):
    from stepper_drivers_msgs.srv import ReadRegister, WriteRegister
    bench = ShippedParams(procs, ros)
    read = ReadRegister.Request(address='1063', data_type='u16')    # VELOCITY_WINDOW_TIME
    before = bench.call('axis1', 'read_register', read, ReadRegister)
    assert before.success, before.message
    r = bench.call('axis1', 'write_register',
                   WriteRegister.Request(address='1063', data_type='u16',
                                         value=before.value + 1), WriteRegister)
    assert not r.success
    assert 'raw writes are disabled' in r.message
    assert 'drives.axis1.allow_raw_write' in r.message
    after = bench.call('axis1', 'read_register', read, ReadRegister)
    assert after.success and after.value == before.value


# ------------------------------------------------------------------------------ SROS2
def _fake_library(tmp_path: pathlib.Path, name: str, content: bytes) -> str:
    path = tmp_path / name
    path.write_bytes(b'\x7fELF' + b'\0' * 64 + content + b'\0' * 64)
    return str(path)


def test_security_plugins_are_found_by_their_namespace(tmp_path):
    with_plugins = _fake_library(
        tmp_path, 'libfastrtps.so.2.14',
        b'_ZN8eprosima8fastrtps4rtps8security15SecurityManager4initEv')
    fast_dds_3 = _fake_library(tmp_path, 'libfastdds.so.3.1',
                               b'N8eprosima7fastdds4rtps8security5PKIDHE')
    without = _fake_library(tmp_path, 'libfastrtps.so.2.13',
                            b'_ZN8eprosima8fastrtps4rtps15MessageReceiver')
    assert dds_security.problem('rmw_fastrtps_cpp', [with_plugins]) == ''
    assert dds_security.problem('rmw_fastrtps_dynamic_cpp', [fast_dds_3]) == ''
    line = dds_security.problem('rmw_fastrtps_cpp', [without])
    assert line.startswith('ROS_SECURITY_ENABLE=true, but the Fast DDS of rmw_fastrtps_cpp '
                           f'({without}) has no DDS-Security plugins')
    assert 'docs/security.md' in line and '\n' not in line
    # what it cannot tell, the rmw decides: another rmw, no library, an unreadable one
    assert dds_security.problem('rmw_cyclonedds_cpp', [without]) == ''
    assert dds_security.problem('rmw_fastrtps_cpp', []) == ''
    assert dds_security.problem('rmw_fastrtps_cpp', [str(tmp_path / 'gone.so')]) == ''
    # rcl/security.c: only the exact string 'true' turns security on
    assert dds_security.security_requested({'ROS_SECURITY_ENABLE': 'true'})
    for value in ('', 'True', '1', 'false'):
        assert not dds_security.security_requested({'ROS_SECURITY_ENABLE': value})


def test_the_fast_dds_library_of_this_process_is_found():
    from rclpy.utilities import get_rmw_implementation_identifier
    if not get_rmw_implementation_identifier().startswith('rmw_fastrtps'):
        pytest.skip('the rmw here is not rmw_fastrtps')
    libraries = dds_security.mapped_fast_dds_libraries()
    assert libraries and all(pathlib.Path(p).is_file() for p in libraries), libraries


NO_PLUGINS = dds_security.startup_problem({'ROS_SECURITY_ENABLE': 'true'})


@pytest.mark.skipif(not NO_PLUGINS, reason="this ROS install's middleware has the security "
                    'plugins (or cannot be asked): nodes start secured there')
@pytest.mark.parametrize('exe, env', [
    (f'{v}_node', {'ROS_SECURITY_ENABLE': 'true'}) for v in KEYS] + [
    ('rd4_lifecycle_node', {'ROS_SECURITY_ENABLE': 'true'}),
    # as docs/security.md sets it up: a keystore with the node's enclave, Enforce
    ('rd4_node', {'ROS_SECURITY_ENABLE': 'true', 'ROS_SECURITY_STRATEGY': 'Enforce',
                  'ROS_SECURITY_KEYSTORE': '{keystore}'}),
])
def test_a_node_asked_for_sros2_without_security_plugins_ends_with_one_line(
        procs, tmp_path, exe, env):
    keystore = tmp_path / 'keystore'
    (keystore / 'enclaves' / 'rd4_node').mkdir(parents=True)
    env = {k: v.format(keystore=keystore) for k, v in env.items()}
    vendor = exe.removesuffix('_node').removesuffix('_lifecycle')
    args = [executable('stepper_drivers', exe), '--ros-args',
            '--params-file', str(CONFIG / f'{vendor}.yaml')]
    if 'ROS_SECURITY_KEYSTORE' in env:
        args += ['--enclave', '/rd4_node']
    p = procs.start(exe, args, env)
    code = p.proc.wait(timeout=EXIT_TIMEOUT_S)
    lines = p.output().strip().splitlines()
    assert code == 2, f'{exe} exited with {code}:\n{p.output()}'
    assert lines == [f'{exe}: {NO_PLUGINS}'], lines


# ------------------------------------------------------------------------------ the page's policy
SECURITY_DOC = ROOT / 'docs' / 'security.md'
FENCE = re.compile(r'^ *```(\w*)\n(.*?)^ *```$', re.M | re.S)


def doc_blocks(lang: str) -> list[str]:
    """The fenced code blocks of docs/security.md in that language, in page order."""
    return [body for kind, body in FENCE.findall(SECURITY_DOC.read_text()) if kind == lang]


def page_policy() -> ET.Element:
    """The policy of docs/security.md as sros2 holds it: lxml's etree.parse keeps comments and
    processing instructions as children of the elements they are in, so they are here too."""
    (policy,) = [b for b in doc_blocks('xml') if '<policy ' in b]
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True, insert_pis=True))
    return ET.fromstring(policy.encode(), parser=parser)


def _shown(child: ET.Element) -> str:
    if child.tag is ET.Comment:
        return f'the comment <!--{child.text}-->'
    if child.tag is ET.ProcessingInstruction:
        return f'the processing instruction <?{child.text}?>'
    attributes = ''.join(f' {k}="{v}"' for k, v in child.attrib.items())
    return f'<{child.tag}{attributes}>'


def policy_walk_errors(policy: ET.Element) -> list[str]:
    """What sros2 0.13 trips over in a policy. generate_artifacts walks `for enclave in
    policy.find('enclaves')` and makes an enclave of `enclave.get('path')` for every child: a
    comment there is an enclave without a path ("failed to validate namespace"). Each enclave's
    <profiles> holds <profile ns=... node=...> and nothing else either."""
    errors = []
    if policy.tag != 'policy' or policy.get('version') != '0.2.0':
        errors.append(f'the root is {_shown(policy)}, not <policy version="0.2.0">')
    enclaves = policy.find('enclaves')
    if enclaves is None:
        return [*errors, 'no <enclaves>']
    for enclave in enclaves:
        if enclave.tag != 'enclave' or not enclave.get('path', '').startswith('/'):
            errors.append(f'<enclaves> holds {_shown(enclave)}, not an <enclave path="/...">')
            continue
        profiles = enclave.findall('profiles')
        if len(profiles) != 1:
            errors.append(f'{_shown(enclave)} has {len(profiles)} <profiles>, not one')
        for profile in (p for ps in profiles for p in ps):
            if profile.tag != 'profile' or not (profile.get('ns') and profile.get('node')):
                errors.append(f'<profiles> of {_shown(enclave)} holds {_shown(profile)}, not a '
                              '<profile ns="..." node="...">')
    return errors


def test_generate_artifacts_finds_an_enclave_path_in_every_child_of_enclaves():
    policy = page_policy()
    errors = policy_walk_errors(policy)
    assert not errors, '\n'.join(errors)
    # the identities generate_artifacts creates, in its order: the enclaves of steps 1 and 3
    identities = [enclave.get('path') for enclave in policy.find('enclaves')]
    text = SECURITY_DOC.read_text()
    created = re.findall(r'ros2 security create_enclave \S+ (\S+)', text)
    (loop,) = re.findall(r'^for e in (.*); do\n +ros2 security create_permission ', text, re.M)
    assert identities == created == loop.split()


def test_the_policy_walk_sees_a_comment_among_the_enclaves():
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True, insert_pis=True))
    policy = ET.fromstring(
        '<policy version="0.2.0"><enclaves><!-- the driver -->'
        '<enclave path="/a"><!-- inside: not walked --><profiles><!-- nor here -->'
        '<profile ns="/" node="n"/><profile node="m"/></profiles></enclave>'
        '</enclaves></policy>', parser=parser)
    assert policy_walk_errors(policy) == [
        '<enclaves> holds the comment <!-- the driver -->, not an <enclave path="/...">',
        '<profiles> of <enclave path="/a"> holds the comment <!-- nor here -->, not a '
        '<profile ns="..." node="...">',
        '<profiles> of <enclave path="/a"> holds <profile node="m">, not a '
        '<profile ns="..." node="...">']


def test_every_signing_step_exports_the_same_domain_id():
    """create_keystore signs the domain ID into the governance, create_enclave,
    create_permission and generate_artifacts into the permissions, each from the ROS_DOMAIN_ID
    of its own shell; the secured nodes run in the domain the files are made for."""
    steps = [b for b in doc_blocks('bash')
             if re.search(r'ros2 security (create_|generate_artifacts)|ROS_SECURITY_ENABLE', b)]
    assert len(steps) >= 3
    domains = {re.search(r'ros2 security \w+|ros2 run \w+ \w+', b)[0]:
               re.findall(r'^export ROS_DOMAIN_ID=(\d+)\b', b, re.M) for b in steps}
    assert all(len(d) == 1 for d in domains.values()), f'export ROS_DOMAIN_ID: {domains}'
    assert len({d for (d,) in domains.values()}) == 1, domains


def test_the_run_example_starts_the_node_and_drives_the_policy_is_made_for():
    (run,) = [b for b in doc_blocks('bash') if '--enclave' in b]
    params_file = re.search(r'rd4_node --ros-args --params-file (\S+)', run)[1]
    enclave = re.search(r'--enclave (\S+)', run)[1]
    assert params_file.startswith('config/') and (ROOT / params_file).is_file(), params_file
    (node_name, settings), = yaml.safe_load((ROOT / params_file).read_text()).items()
    drives = set(settings['ros__parameters']['drives'])
    enclaves = {e.get('path'): e for e in page_policy().find('enclaves')
                if e.tag == 'enclave'}
    assert {e for b in doc_blocks('bash')
            for e in re.findall(r'ROS_SECURITY_ENCLAVE_OVERRIDE=(\S+)', b)} <= set(enclaves)
    (profile,) = enclaves[enclave].iter('profile')
    assert (profile.get('ns'), profile.get('node')) == ('/', node_name)
    for path, element in enclaves.items():
        # ~/<drive>/<name> in the node's profile, /<node>/<drive>/<name> in the others
        relative = []
        for name in (n.text for n in element.iter() if n.tag in ('topic', 'service', 'action')):
            if name.startswith('~/'):
                relative.append(name[2:])
            elif name.count('/') > 1:
                assert name.startswith(f'/{node_name}/'), (path, name, params_file)
                relative.append(name[len(node_name) + 2:])
        used = {name.split('/')[0] for name in relative if '/' in name}
        assert used <= drives, (path, used, params_file)
        if path == enclave:
            assert used == drives, (path, used, params_file)
