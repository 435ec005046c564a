"""R.T.A. X-MIND K on its ASCII RS-485 line: the vendor's entry (make_bus, make_drive, validate,
VENDOR); the line itself is `protocol.xmind_k_bus.XmindKBus`.

How the common contract maps onto the drive (docs/xmind_k.md has the full table):

- moves and free runs are written to the RAM cells 228-230 (`WN`) and started with `PS`; the
  EEPROM cells 100-227 are never written at run time, presets (`WS`) only when they differ;
- the drive answers nothing while it executes a program (§3), so while busy the position is
  estimated from the commanded profile (DriveState.position_estimated) and corrected by `QA` as
  soon as the drive answers again; velocity cannot be read at all (velocity_valid = False);
- a velocity change while running is stop (`ES`), wait until the drive answers, rewrite, restart;
- stop = `ES` for a free run (the only thing ES stops, §4.2.7), `EE` otherwise; quick stop = `EE`;
  a bus closed with drives in motion gets a broadcast `99EE`;
- enable = `CY`, disable = `CN` (not readable back, so tracked); what is checked on the wire
  before every start is FA (no protection) and the power-cycle flag (the drive still runs the
  power-on session in which it got CY); homing = zero search (03) plus counter reset (60);
  fault reset does not exist (RefusedError); every preset is already stored;
- every operation of more than one string is step-wise (contract/drive.py): 0.0 is yielded
  between strings, waits are yields; `stop()` is one string. A 9600 baud string takes 20-50 ms.
- the drives of one line start together with `start_together` (a job for the bus owner): each
  run stored, then one broadcast `99PS` where every drive that hears it is known to hold what
  was stored for it (`broadcast_refusal`), else one `PS` per drive; `probe_line` asks the
  addresses no drive of the node has.

The package: the parameters, their defaults and the per-drive rules in `settings.py` (which the
entry and the drive classes both import, never the other way round), the drive class
`XmindKDrive` in `drive.py` on its bases `maintenance.py` (fault reset, save, raw registers) and
`link.py` (its strings, connect, the status check); the drive is
silent while it runs a program (§3), so read_state, stop, a velocity change and homing all work
in drive.py on the same running `DriveProgram`, its `Estimate` (`program.py`) and the epoch. The
group start and `XmindKGroupBus` are in `group.py`, the chained runs and `XmindKChainBus` (the
node's bus) in `chain.py`, the bus scanner in `scan.py`.
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract import param_rules
from ...contract.drive import Vendor
from ...protocol.xmind_k_bus import XmindKBus
from . import scan as xmind_k_scan
from . import settings
from .chain import ChainMove, XmindKChainBus, start_chained
from .drive import XmindKDrive
from .group import (
    GroupMove,
    GroupStart,
    XmindKGroupBus,
    broadcast_refusal,
    line_refusal,
    probe_line,
    start_together,
)
from .program import DriveProgram, Estimate
from .settings import HOMING_METHODS, PARAMS, _check_address, _check_drive

__all__ = ['HOMING_METHODS', 'PARAMS', 'VENDOR', 'ChainMove', 'DriveProgram', 'Estimate',
           'GroupMove', 'GroupStart', 'XmindKChainBus', 'XmindKDrive', 'XmindKGroupBus',
           'broadcast_refusal', 'line_refusal', 'make_bus', 'make_drive', 'probe_line',
           'start_chained', 'start_together', 'validate']


def validate(params: Mapping[str, Any]) -> list[str]:
    """The X-MIND K's parameter rules on the node's parameters (param_rules), at start-up and for
    every run-time change: one address per drive on the line, and per drive homing method and
    resolution. Pure: it never builds a drive (a drive records its address in bus.addresses)."""
    taken: dict[str, int] = {}
    url = str(params.get('port', ''))
    errors = []
    for name in param_rules.drive_names(params):
        number = int(param_rules.drive_params(params, name).get('address', 0))
        errors += param_rules.first_error(_check_address, name, number, taken, url)
        taken.setdefault(name, number)
    return errors + param_rules.check_each(params, None, _check_drive)


# ---------------------------------------------------------------------------------- vendor
def make_bus(params: Mapping[str, Any]) -> XmindKChainBus:
    return XmindKChainBus(VENDOR.with_defaults(params))


def make_drive(bus: XmindKBus, name: str, params: Mapping[str, Any]) -> XmindKDrive:
    return XmindKDrive(bus, name, params)


VENDOR = Vendor(
    name='X-MIND K',
    params=PARAMS,
    make_bus=make_bus,
    make_drive=make_drive,
    drive_defaults=settings.DRIVE_DEFAULTS,
    # At 9600 baud two axes need segments of 0.85-1.5 s (a move: WN, PS and the status strings
    # per axis): a 3 s MoveIt plan of about 1 rad becomes 2-3 segments that pass 0.15-0.45 rad
    # from its points (docs/moveit.md). The default bound takes such plans and refuses coarser.
    joint_defaults={'path_bound': 0.5},
    validate=validate,
    scanner=xmind_k_scan.SCANNER,
)
