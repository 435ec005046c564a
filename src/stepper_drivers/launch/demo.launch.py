"""Everything the demo uses: the four vendors' simulators and driver nodes (and the CAN broker).

Each vendor's own launch file with sim:=true, on the ports of the params files in config/
(X-PLUS MT 127.0.0.1:1502, RD4 /tmp/rd4_sim, X-MIND K /tmp/xmind_k_sim.tty, CAN broker
127.0.0.1:29536). Then drive them with stepperctl (ros2 run stepper_drivers stepperctl list).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import GroupAction, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource


def include(launch_file):
    path = os.path.join(get_package_share_directory('stepper_drivers'), 'launch', launch_file)
    # Launch configurations are global to a launch run: IncludeLaunchDescription sets its
    # arguments in the current scope and DeclareLaunchArgument keeps a value already set, so the
    # first file's params_file default would configure every later vendor's node. A scoped group
    # (launch.actions.GroupAction, scoped=True) drops what the included file sets when it ends.
    return GroupAction([IncludeLaunchDescription(PythonLaunchDescriptionSource(path),
                                                 launch_arguments={'sim': 'true'}.items())],
                       scoped=True)


def generate_launch_description():
    return LaunchDescription([
        include('xplus_mt.launch.py'),
        include('rd4.launch.py'),
        include('xmind_k.launch.py'),
        include('vector_step.launch.py'),
    ])
