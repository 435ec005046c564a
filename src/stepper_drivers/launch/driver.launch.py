"""One vendor's node with its params file, for every vendor of the table (vendor_table.py).

    ros2 launch stepper_drivers driver.launch.py vendor:=rd4            the node, config/rd4.yaml
    ros2 launch stepper_drivers driver.launch.py vendor:=rd4 sim:=true  ... and its simulator
    ros2 launch stepper_drivers rd4.launch.py sim:=true                 the same, by the vendor's
                                                                        own file name

`<key>.launch.py` are symbolic links to this file: the name it is loaded under gives the vendor
when no vendor:= is passed. sim:=true also starts `<key>_sim` with config/<key>_sim.yaml and the
helpers the simulator needs (the Vector Step's loopback CAN broker on the port its params files
name). lifecycle:=true starts the managed node `<key>_lifecycle_node` instead, under the plain
node's name, so the same params file applies; a lifecycle manager configures and activates it
(docs/interface.md). On a real bus pass params_file:=<your file> (`stepperctl scan <key>
--write-yaml` writes one).
"""

import os

from ament_index_python.packages import get_package_prefix, get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

# The vendor table is plain data (no rclpy, no vendor module): safe to import in a launch file.
from stepper_drivers.vendors.table import BY_KEY, KEYS


def _vendor_of_file_name() -> str:
    """'rd4' when this file is loaded as rd4.launch.py, '' as driver.launch.py."""
    key = os.path.basename(__file__).removesuffix('.launch.py')
    return key if key in BY_KEY else ''


def _actions(context):
    key = LaunchConfiguration('vendor').perform(context)
    if key not in BY_KEY:
        raise RuntimeError(f'vendor:={key!r} is not a vendor of stepper_drivers (one of: '
                           f'{", ".join(KEYS)})')
    row = BY_KEY[key]
    config = os.path.join(get_package_share_directory('stepper_drivers'), 'config')
    params_file = LaunchConfiguration('params_file').perform(context) or \
        os.path.join(config, row.params_file)
    sim = IfCondition(LaunchConfiguration('sim'))
    lifecycle = LaunchConfiguration('lifecycle')
    helpers = os.path.join(get_package_prefix('stepper_sim'), 'lib', 'stepper_sim')
    return [
        # helpers are plain processes (no --ros-args), started before the simulator
        *(ExecuteProcess(cmd=[os.path.join(helpers, name), *args], condition=sim,
                         output='screen') for name, *args in row.sim_helpers),
        Node(package='stepper_sim', executable=row.sim, name=row.sim,
             parameters=[os.path.join(config, row.sim_params_file)], condition=sim,
             output='screen'),
        Node(package='stepper_drivers', executable=row.node, name=row.node,
             parameters=[params_file], output='screen', condition=UnlessCondition(lifecycle)),
        LifecycleNode(package='stepper_drivers', executable=row.lifecycle_node, name=row.node,
                      namespace='', parameters=[params_file], output='screen',
                      condition=IfCondition(lifecycle)),
    ]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('vendor', default_value=_vendor_of_file_name(),
                              description=f'the vendor key: {", ".join(KEYS)}'),
        DeclareLaunchArgument('params_file', default_value='',
                              description="the node's params file (default: "
                              'config/<vendor>.yaml of this package)'),
        DeclareLaunchArgument('sim', default_value='false',
                              description='also start the simulator <vendor>_sim '
                              '(config/<vendor>_sim.yaml) and its helpers'),
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: the managed (lifecycle) node '
                              '<vendor>_lifecycle_node, waiting for configure and activate'),
        OpaqueFunction(function=_actions),
    ])
