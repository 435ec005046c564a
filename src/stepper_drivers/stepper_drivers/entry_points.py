"""Executables: one function per vendor node, <key>_node, made from the vendor table (console
scripts in setup.py). Vendor modules are imported only when used."""

from __future__ import annotations

import importlib
import sys

from .vendor_table import BY_NODE, ROWS


def run(exe: str, argv: list[str] | None = None) -> int:
    import rclpy

    from .node import DriveNode, spin_node
    from .params import ParameterError, declare_all, non_ros_args

    module = importlib.import_module(BY_NODE[exe].module)
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
    rclpy.init(args=argv)
    try:
        node = DriveNode(vendor, exe, lambda n: declare_all(n, vendor, argv, module.validate))
    except ParameterError as e:
        print(f'{exe}: {e}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    spin_node(node)
    return 0


def _executable(exe: str):
    def main() -> None:
        sys.exit(run(exe))
    main.__name__ = main.__qualname__ = exe
    main.__doc__ = f'The {exe} executable.'
    return main


for _row in ROWS:
    globals()[_row.node] = _executable(_row.node)     # xplus_mt_node(), rd4_node(), ...


def socketcand_broker() -> None:
    from .protocol.socketcand_broker import main
    sys.exit(main())


def stepperctl() -> None:
    from .cli.main import main
    sys.exit(main())
