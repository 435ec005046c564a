"""AEC Vector Step over CANopen (DS-301 V4.01 / DSP-402 V1.1): the vendor's entry (make_bus,
make_drive, validate and its node-ID rules, VENDOR).

Objects, codes and texts come from `regmap.py` (which cites the sections of the manual
`aec_vector_step_canopen_it.txt`), the CiA 402 tables, walker and modes from
profiles/cia402/, the bus and node plumbing from `protocol/canopen_link.py`. The package, split
along the seam ros2_canopen uses (the PDO/SDO image apart from the CiA 402 state machine and
its modes): the parameters, their defaults and the per-drive rules in `settings.py` (which the
entry and the drive classes both import, never the other way round), the drive class
`VectorStepDrive` in `drive.py` (the CiA 402 drive, fault reset, save) on its bases
`ProcessImage` (`pdo.py`: the PDO set written at every boot, the TxPDO cache and its coherence,
snapshot vouching), `CanopenNode` (`node.py`: boot, identity, liveness, SDO access) and
`ModeCommands` (`modes.py`: profile position, JOG, homing, interpolated position, stop); the
bus scanner in `scan.py`. No rclpy.

After the boot the state comes from TxPDOs, so `read_state()` costs no bus traffic but one SDO
read of 0x6064 for a statusword that says the axis stands; the heartbeat consumer and the
boot-up latch turn a silent or rebooted node into a LinkError (the node layer reconnects).
"""

from __future__ import annotations

from typing import Any, Mapping

from ...contract import param_rules
from ...contract.drive import Bus, Vendor
from ...protocol.canopen_link import MASTER, CanBus
from . import regmap as vm
from . import scan as vector_step_scan
from . import settings
from .drive import VectorStepDrive
from .node import parse_address
from .pdo import QUIET_CHECK_S
from .settings import MASTER_HEARTBEAT_PERIODS, PARAMS, SYNC_TIMEOUT_MIN_PERIODS, _check_drive

# what other code takes from the package
__all__ = ['MASTER_HEARTBEAT_PERIODS', 'PARAMS', 'QUIET_CHECK_S',
           'SYNC_TIMEOUT_MIN_PERIODS', 'VENDOR', 'VectorStepDrive', 'make_bus', 'make_drive',
           'parse_address', 'validate']


def _node_id_errors(params: Mapping[str, Any], bus: Mapping[str, Any]) -> list[str]:
    """Two drives with one node-ID, or a drive on the node's own heartbeat node-ID: the rules
    CanBus.claim applies when the drives are made (same messages). `bus`: the bus parameters
    with their defaults."""
    taken: dict[int, str] = {}
    if int(bus['can.master_heartbeat_ms']):
        taken[int(bus['can.master_node_id'])] = MASTER
    errors = []
    for name in param_rules.drive_names(params):
        node_id = int(VENDOR.with_defaults(param_rules.drive_params(params, name))['node_id'])
        other = taken.setdefault(node_id, name)
        if other == MASTER:
            errors.append(f'drives.{name}.node_id: {node_id} is can.master_node_id, the '
                          "node-ID of this node's own heartbeat (allowed: 1..127, one per "
                          'device)')
        elif other != name:
            errors.append(f'drives.{name}.node_id: {node_id} is already the node-ID of '
                          f'drive {other!r} on this bus (allowed: 1..127, one per drive)')
    return errors


def validate(params: Mapping[str, Any]) -> list[str]:
    """The Vector Step's parameter rules on the node's parameters (param_rules), at start-up
    and for every run-time change: node-IDs, and per drive bit rate, homing method, heartbeat,
    SYNC watchdog and the node's own heartbeat."""
    bus = VENDOR.with_defaults(param_rules.bus_params(params))
    return _node_id_errors(params, bus) + param_rules.check_each(
        params, None, lambda name, view: _check_drive(
            name, view, int(bus['can.master_heartbeat_ms']), float(bus['can.sync_period_s'])))


def make_bus(params: Mapping[str, Any]) -> CanBus:
    params = VENDOR.with_defaults(params)
    return CanBus(interface=str(params['can.interface']), channel=str(params['can.channel']),
                  bitrate=int(params['can.bitrate']), host=str(params['can.host']),
                  port=int(params['can.port']), timeout_s=float(params['timeout_s']),
                  sync_period_s=float(params['can.sync_period_s']),
                  master_node_id=int(params['can.master_node_id']),
                  master_heartbeat_ms=int(params['can.master_heartbeat_ms']),
                  owner_thread_priority=int(params.get('owner_thread_priority', 0)))


def make_drive(bus: Bus, name: str, params: Mapping[str, Any]) -> VectorStepDrive:
    return VectorStepDrive(bus, name, params)


VENDOR = Vendor(name='AEC Vector Step', params=PARAMS, make_bus=make_bus, make_drive=make_drive,
                drive_defaults=settings.DRIVE_DEFAULTS,
                validate=validate, share_files={'can.eds_file': vm.EDS_FILE},
                scanner=vector_step_scan.SCANNER)
