"""A vendor's DriveNode built in this test process from its config/<key>.yaml: the constructor
declares the parameters and makes the drives; nothing is opened or spun. Tests that build one
take the `offline_rclpy` fixture (conftest.py), which shuts rclpy down at their end.
"""

import importlib

from rosharness import CONFIG
from stepper_drivers.vendors.table import BY_KEY


def make_node(key: str, *ros_args: str, vendor=None):
    """The DriveNode of `key` with config/<key>.yaml and more ROS arguments; the node layer uses
    rclpy's default context, so the args are given to it as to rclpy.init."""
    import rclpy
    from stepper_drivers.ros.node import DriveNode
    from stepper_drivers.ros.params import declare_all
    module = importlib.import_module(BY_KEY[key].module)
    vendor = vendor or module.VENDOR
    args = ['test', '--ros-args', '--params-file', str(CONFIG / f'{key}.yaml'), *ros_args]
    rclpy.try_shutdown()
    rclpy.init(args=args)
    return DriveNode(vendor, f'{key}_node',
                     lambda n: declare_all(n, vendor, args, module.validate))
