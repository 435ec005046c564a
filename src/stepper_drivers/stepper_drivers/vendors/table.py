"""The vendors, one row each: what the executables, setup.py, stepperctl, launch and tests read.

Plain data, no imports of the package (both setup.py files load this file with runpy, without
rclpy or the vendor modules). Everything else about a vendor follows from its key by convention:

    executable            <key>_node and <key>_lifecycle_node (stepper_drivers.ros.entry_points),
                          <key>_sim (stepper_sim)
    params files          config/<key>.yaml (node named <key>_node), config/<key>_sim.yaml
    launch file           src/stepper_drivers/launch/driver.launch.py vendor:=<key> (sim:=true
                          adds the sim); <key>.launch.py, a link to it, for the four shipped
    driver page           docs/<key>.md
    vendor module         `module`: VENDOR (drive.Vendor) and validate(params) -> list[str]
    bus scanner           VENDOR.scanner, in vendors/<key>_scan.py: `stepperctl scan <key>`
                          (None: the vendor has no scan command)

docs/adding_a_vendor.md walks through adding a row.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class VendorRow:
    key: str               # 'rd4': names the executables, files and the stepperctl scan command
    title: str             # 'Lika RD4', for help texts
    module: str            # the vendor module: VENDOR (with its scanner) and validate(params)
    simulator: str         # console script target of <key>_sim: 'package.module:function'
    address_param: str     # the per-drive address parameter ('node_id', 'unit_id', ...)
    link_param: str = 'port'   # the parameter the node and its simulator share (the link)
    # other processes `driver.launch.py vendor:=<key> sim:=true` starts before the simulator,
    # each a stepper_sim console script '<name> = stepper_sim.<name>:main' (src/stepper_sim/
    # setup.py) and its arguments: (name, arg, ...)
    sim_helpers: tuple[tuple[str, ...], ...] = ()

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


ROWS: tuple[VendorRow, ...] = (
    VendorRow('xplus_mt', 'R.T.A. X-PLUS MT', 'stepper_drivers.vendors.xplus_mt',
              'stepper_sim.xplus_mt.sim:main', 'unit_id'),
    VendorRow('rd4', 'Lika RD4', 'stepper_drivers.vendors.rd4', 'stepper_sim.rd4.sim:main',
              'node_id'),
    VendorRow('xmind_k', 'R.T.A. X-MIND K', 'stepper_drivers.vendors.xmind_k',
              'stepper_sim.xmind_k.sim:main', 'address'),
    VendorRow('vector_step', 'AEC Vector Step', 'stepper_drivers.vendors.vector_step',
              'stepper_sim.vector_step.sim:main', 'node_id', link_param='can.port',
              # the loopback CAN broker on can.port of both params files
              sim_helpers=(('socketcand_broker', '--port', '29536'),)),
)

BY_KEY = {row.key: row for row in ROWS}
BY_NODE = {row.node: row for row in ROWS}
BY_LIFECYCLE_NODE = {row.lifecycle_node: row for row in ROWS}
KEYS = tuple(BY_KEY)
