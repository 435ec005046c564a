"""The capabilities each vendor implements are those docs/adding_a_vendor.md's table says, and
the bus owner, the poll group and the follower use one only where it is implemented."""

from __future__ import annotations

import importlib
import pathlib
import re
import typing

import pytest
from stepper_drivers.contract import capabilities
from stepper_drivers.contract.drive import Bus, Drive
from stepper_drivers.vendors.table import ROWS

DOC = pathlib.Path(__file__).resolve().parents[4] / 'docs' / 'adding_a_vendor.md'
TITLES = {'X-PLUS MT': 'xplus_mt', 'RD4': 'rd4', 'X-MIND K': 'xmind_k',
          'Vector Step': 'vector_step'}
NAMES = [n for n in dir(capabilities) if isinstance(getattr(capabilities, n), type)
         and getattr(capabilities, n).__module__ == capabilities.__name__]


def doc_table() -> dict[str, tuple[str, set[str]]]:
    """{capability: ('Drive' or 'Bus', {vendor key})} from the page's capability table."""
    out = {}
    for name, of, _what, who in re.findall(
            r'^\| `(\w+)` \| (Drive|Bus) \| (.*?) \| (.*?) \|$', DOC.read_text(), re.M):
        out[name] = (of, {key for title, key in TITLES.items() if title in who})
    return out


def classes(key: str) -> tuple[type, type]:
    """(drive class, bus class) of a vendor: what make_drive and make_bus return."""
    module = importlib.import_module(f'stepper_drivers.vendors.{key}')
    return (typing.get_type_hints(module.make_drive)['return'],
            typing.get_type_hints(module.make_bus)['return'])


def test_the_page_lists_every_capability_once():
    assert sorted(doc_table()) == sorted(NAMES)


@pytest.mark.parametrize('name', NAMES)
def test_a_capability_is_implemented_where_the_page_says_and_nowhere_else(name):
    of, vendors = doc_table()[name]
    capability = getattr(capabilities, name)
    for row in ROWS:
        drive, bus = classes(row.key)
        assert issubclass(drive, Drive) and issubclass(bus, Bus)
        cls = drive if of == 'Drive' else bus
        assert issubclass(cls, capability) == (row.key in vendors), (name, row.key, cls)
