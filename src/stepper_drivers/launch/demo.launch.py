"""Everything the demo uses: every vendor's simulator and driver node (and the CAN broker).

driver.launch.py with vendor:=<key> sim:=true for each vendor of the table, on the ports of the
params files in config/ (X-PLUS MT 127.0.0.1:1502, RD4 /tmp/rd4_sim, X-MIND K /tmp/xmind_k_sim.tty,
CAN broker 127.0.0.1:29536). Then drive them with stepperctl (ros2 run stepper_drivers stepperctl
list).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import GroupAction, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource

# The vendor table is plain data (no rclpy, no vendor module): safe to import in a launch file.
from stepper_drivers.vendors.table import KEYS


def include(vendor):
    path = os.path.join(get_package_share_directory('stepper_drivers'), 'launch',
                        'driver.launch.py')
    # Launch configurations are global to a launch run: IncludeLaunchDescription sets its
    # arguments in the current scope and DeclareLaunchArgument keeps a value already set, so a
    # value one include sets would reach every later include (a params_file:= or a default of
    # the included file would configure every later vendor's node). A scoped group
    # (launch.actions.GroupAction, scoped=True) drops what the included file sets when it ends.
    return GroupAction([IncludeLaunchDescription(PythonLaunchDescriptionSource(path),
                                                 launch_arguments={'vendor': vendor,
                                                                   'sim': 'true'}.items())],
                       scoped=True)


def generate_launch_description():
    return LaunchDescription([include(vendor) for vendor in KEYS])
