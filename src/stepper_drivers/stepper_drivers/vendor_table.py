"""The vendors, one row each: what the executables, both setup.py, stepperctl and the tests read.

Plain data, no imports of the package (both setup.py files load this file with runpy, without
rclpy or the vendor modules). Everything else about a vendor follows from its key by convention:

    executable            <key>_node and <key>_lifecycle_node (stepper_drivers.entry_points),
                          <key>_sim (stepper_sim)
    params files          config/<key>.yaml (node named <key>_node), config/<key>_sim.yaml
    launch file           src/stepper_drivers/launch/<key>.launch.py (sim:=true adds the sim)
    driver page           docs/<key>.md
    vendor module         `module`: VENDOR (drive.Vendor) and validate(params) -> list[str]

docs/adding_a_vendor.md walks through adding a row.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class VendorRow:
    key: str               # 'rd4': names the executables, files and the stepperctl scan command
    title: str             # 'Lika RD4', for help texts
    module: str            # the vendor module: VENDOR and validate(params)
    simulator: str         # console script target of <key>_sim: 'package.module:function'
    address_param: str     # the per-drive address parameter ('node_id', 'unit_id', ...)
    link_param: str = 'port'   # the parameter the node and its simulator share (the link)
    # other executables `<key>.launch.py sim:=true` starts: stepper_sim console scripts
    # '<name> = stepper_sim.<name>:main' (src/stepper_sim/setup.py)
    sim_helpers: tuple[str, ...] = ()
    scan_help: str = ''    # `stepperctl scan <key>` help; '' = no scanner (cli/scan.py)
    scan_hint: str = ''    # what to check when a scan finds nothing

    @property
    def node(self) -> str:
        return f'{self.key}_node'

    @property
    def lifecycle_node(self) -> str:
        """The managed (lifecycle) variant; its node is named like the plain one."""
        return f'{self.key}_lifecycle_node'

    @property
    def sim(self) -> str:
        return f'{self.key}_sim'

    @property
    def params_file(self) -> str:
        return f'{self.key}.yaml'

    @property
    def sim_params_file(self) -> str:
        return f'{self.key}_sim.yaml'

    @property
    def launch_file(self) -> str:
        return f'{self.key}.launch.py'


ROWS: tuple[VendorRow, ...] = (
    VendorRow('xplus_mt', 'R.T.A. X-PLUS MT', 'stepper_drivers.vendors.xplus_mt',
              'stepper_sim.xplus_mt_sim:main', 'unit_id',
              scan_help='R.T.A. X-PLUS MT: Modbus TCP hosts and unit ids',
              scan_hint='check --host/--port (factory 192.168.1.10:502) and that the drive is '
                        'powered'),
    VendorRow('rd4', 'Lika RD4', 'stepper_drivers.vendors.rd4', 'stepper_sim.rd4_sim:main',
              'node_id',
              scan_help='Lika RD4: Modbus RTU unit ids on a serial line',
              scan_hint="check the port, the A/B wiring, and --baudrate/--parity against the "
                        "units' dip-switches (factory 9600 8E1)"),
    VendorRow('xmind_k', 'R.T.A. X-MIND K', 'stepper_drivers.vendors.xmind_k',
              'stepper_sim.xmind_k_sim:main', 'address',
              scan_help='R.T.A. X-MIND K: ASCII addresses 00-47 on RS-485',
              scan_hint='check the port and wiring; a drive running a program does not answer '
                        '(§3): stop it (EE) first'),
    VendorRow('vector_step', 'AEC Vector Step', 'stepper_drivers.vendors.vector_step',
              'stepper_sim.vector_step_sim:main', 'node_id', link_param='can.port',
              sim_helpers=('socketcand_broker',),
              scan_help='AEC Vector Step: CANopen node-ids (0x1018)',
              scan_hint='check the CAN interface, the bit rate (Rcanbaud) and the bus '
                        'termination'),
)

BY_KEY = {row.key: row for row in ROWS}
BY_NODE = {row.node: row for row in ROWS}
BY_LIFECYCLE_NODE = {row.lifecycle_node: row for row in ROWS}
KEYS = tuple(BY_KEY)
