"""Executables: main() behind every node executable (console scripts in setup.py, two per row
of the vendor table): <key>_node, the plain node, and <key>_lifecycle_node, the managed variant
(lifecycle_node.py) under the same node name. Vendor modules are imported only when used."""

from __future__ import annotations

import importlib
import os
import sys

from ..vendors.table import BY_LIFECYCLE_NODE, BY_NODE


def run(exe: str, argv: list[str] | None = None) -> int:
    from .process import block_shutdown_signals, spin_node
    block_shutdown_signals()        # before any thread: the node takes its signals (process.py)

    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from . import dds_security
    from .node import DriveNode
    from .params import ParameterError, declare_all, non_ros_args

    row = BY_NODE.get(exe) or BY_LIFECYCLE_NODE[exe]
    managed = exe == row.lifecycle_node
    if managed:
        from .lifecycle_node import ManagedDriveNode as node_class
    else:
        node_class = DriveNode
    module = importlib.import_module(row.module)
    vendor = module.VENDOR
    argv = sys.argv if argv is None else argv
    try:
        extra = non_ros_args(argv)[1:]      # a missing or broken params file fails here
    except ParameterError as e:
        print(f'{exe}: {e}', file=sys.stderr, flush=True)
        return 2
    if extra:
        print(f'{exe}: unexpected arguments {extra}; usage: {exe} --ros-args --params-file '
              'FILE.yaml', file=sys.stderr)
        return 2
    # SROS2 asked for where the middleware has no security plugins: one line, not the rmw's
    # error after rcl's log lines (dds_security.py)
    insecure = dds_security.startup_problem()
    if insecure:
        print(f'{exe}: {insecure}', file=sys.stderr, flush=True)
        return 2
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = node_class(vendor, row.node, lambda n: share_files(
            declare_all(n, vendor, argv, vendor.validate), vendor.share_files))
    except ParameterError as e:
        print(f'{exe}: {e}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    return spin_node(node)


def share_files(cfg, files: dict[str, str]):
    """Fill each bus parameter of `files` left '' with its file in the installed share directory
    of stepper_drivers, found through ROS's package index (a vendor module imports no ROS: it
    names the file relative to that directory). Not installed: left '' (the source tree's)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    for key, relative in files.items():
        if cfg.params.get(key) == '':
            try:
                cfg.params[key] = os.path.join(get_package_share_directory('stepper_drivers'),
                                               relative)
            except PackageNotFoundError:
                pass
    return cfg


def main() -> None:
    """Every node executable (setup.py points each <key>_node and <key>_lifecycle_node here):
    the name it was started under picks the vendor's row, so a new row needs no code here."""
    exe = os.path.basename(sys.argv[0])
    if exe not in BY_NODE and exe not in BY_LIFECYCLE_NODE:
        names = ', '.join(sorted([*BY_NODE, *BY_LIFECYCLE_NODE]))
        print(f'{exe}: not a node executable of the vendor table ({names})', file=sys.stderr)
        sys.exit(2)
    sys.exit(run(exe))
