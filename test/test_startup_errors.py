"""Start-up input errors end every executable with one line naming the problem and exit code 2:
a params file that is missing or not a params file, `drives: []`, a params file written for
another node, a value the vendor refuses. Run through the installed
executables, as `ros2 run` starts them; each must end before it opens any link."""

import re

import pytest
from rosharness import CONFIG, executable
from stepper_drivers.vendors.table import KEYS

VENDORS = KEYS
EXECUTABLES = [('stepper_drivers', f'{v}_node') for v in VENDORS] + \
    [('stepper_sim', f'{v}_sim') for v in VENDORS]
EXIT_TIMEOUT_S = 20.0      # a Python start-up with rclpy takes ~1 s; the machine is shared


def start_up_output(procs, pkg: str, exe: str, *ros_args: str) -> list[str]:
    """Run `exe --ros-args ...`; it must exit with 2. Returns its output (stdout and stderr)."""
    p = procs.start(exe, [executable(pkg, exe), '--ros-args', *ros_args])
    code = p.proc.wait(timeout=EXIT_TIMEOUT_S)
    assert code == 2, f'{exe} exited with {code}:\n{p.output()}'
    return p.output().strip().splitlines()


def config_file(tmp_path, exe: str, replace: tuple[str, str] | None = None) -> str:
    """config/<vendor>[_sim].yaml of this executable, with a regex replacement, in tmp_path."""
    name = exe.removesuffix('_node') + '.yaml'
    text = (CONFIG / name).read_text()
    if replace is not None:
        text, n = re.subn(*replace, text, flags=re.M)
        assert n == 1, f'{replace[0]!r} not in config/{name}'
    f = tmp_path / name
    f.write_text(text)
    return str(f)


@pytest.mark.parametrize('pkg, exe', EXECUTABLES)
def test_a_missing_params_file_is_named(procs, tmp_path, pkg, exe):
    missing = tmp_path / 'no_such.yaml'
    assert start_up_output(procs, pkg, exe, '--params-file', str(missing)) == [
        f'{exe}: params file {missing}: cannot be read (No such file or directory)']


@pytest.mark.parametrize('pkg, exe', EXECUTABLES)
def test_a_params_file_that_is_not_yaml_is_named_with_its_line(procs, tmp_path, pkg, exe):
    # the drives list left open: rcl's YAML parser stops at line 3 of the node's block
    broken = config_file(tmp_path, exe, (r'^    drives: \[(.*)\]$', r'    drives: [\1\n  x: : :'))
    (line,) = start_up_output(procs, pkg, exe, '--params-file', broken)
    assert line.startswith(f'{exe}: params file {broken}: not a ROS 2 params file (Error '), line
    assert re.search(r'line \d+\)$', line), line


@pytest.mark.parametrize('pkg, exe', EXECUTABLES)
def test_an_empty_drives_list_is_refused(procs, tmp_path, pkg, exe):
    empty = config_file(tmp_path, exe, (r'^    drives: \[.*\]$', '    drives: []'))
    message = ('parameter drives: no drive named (allowed: a list of one or more drive names, '
               'each with its drives.<name>.* parameters)' if pkg == 'stepper_drivers' else
               'parameter drives: at least one drive name is needed')
    assert start_up_output(procs, pkg, exe, '--params-file', empty) == [f'{exe}: {message}']


@pytest.mark.parametrize('vendor, other', list(zip(VENDORS, VENDORS[1:] + VENDORS[:1])))
def test_a_params_file_for_another_node_is_named_as_such(procs, vendor, other):
    """A launch that passes the wrong file: rd4_node started with config/xplus_mt.yaml."""
    exe = f'{vendor}_node'
    assert start_up_output(procs, 'stepper_drivers', exe, '--params-file',
                           str(CONFIG / f'{other}.yaml')) == [
        f'{exe}: parameter drives: not set, and no parameter is given for node /{exe} (a params '
        f'file configures the node named by its top-level key: {exe}: in the root namespace, '
        f'/**/{exe}: in any, or /**:)']


def test_a_baud_rate_the_rd4_does_not_have_is_named(procs):
    """14400 is inside the declared range 9600..19200; the RD4's make_bus refuses it (§4.4.2)."""
    (line,) = start_up_output(procs, 'stepper_drivers', 'rd4_node', '--params-file',
                              str(CONFIG / 'rd4.yaml'), '-p', 'baudrate:=14400')
    assert re.fullmatch(r'rd4_node: (parameter )?baudrate: 14400 is not an RD4 baud rate '
                        r'\(allowed: 9600, 19200; .*\)', line), line


@pytest.mark.parametrize('pkg, exe', [('stepper_drivers', 'rd4_node'), ('stepper_sim', 'rd4_sim')])
def test_a_malformed_ros_argument_is_named(procs, pkg, exe):
    (line,) = start_up_output(procs, pkg, exe, '-p', 'baudrate')
    assert line.startswith(f"{exe}: Failed to parse ROS arguments: Couldn't parse parameter "
                           "override rule: '-p baudrate'"), line
