"""The vector_step_sim executable loads the EDS installed with stepper_drivers (an apt-style
install has no source tree for vector_step_map.eds_path() to find)."""

import pathlib

from stepper_sim.vector_step.sim import installed_eds

WS = pathlib.Path(__file__).resolve().parents[4]


def test_the_entry_point_finds_the_installed_eds_of_the_workspace():
    path = installed_eds()
    assert path is not None, 'stepper_drivers not on the ament index: source scripts/env.sh'
    assert pathlib.Path(path) == \
        WS / 'install' / 'stepper_drivers' / 'share' / 'stepper_drivers' / 'config' / \
        'vector_step.eds', path
    assert pathlib.Path(path).read_bytes() == (WS / 'config' / 'vector_step.eds').read_bytes()
