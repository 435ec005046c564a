"""Lika RD4 node with its params file; sim:=true also starts the simulated units (rd4_sim).

The simulator creates the pty symlink /tmp/rd4_sim that config/rd4.yaml opens; on a real line
pass params_file:=<your file> with port: /dev/ttyUSB0 (stepperctl scan rd4 writes one).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory('stepper_drivers'), 'config')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=os.path.join(config, 'rd4.yaml')),
        DeclareLaunchArgument('sim', default_value='false',
                              description='also start rd4_sim (config/rd4_sim.yaml)'),
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: the managed (lifecycle) node, '
                              'rd4_lifecycle_node, waiting for configure and activate'),
        Node(package='stepper_sim', executable='rd4_sim', name='rd4_sim',
             parameters=[os.path.join(config, 'rd4_sim.yaml')],
             condition=IfCondition(LaunchConfiguration('sim')), output='screen'),
        Node(package='stepper_drivers', executable='rd4_node', name='rd4_node',
             parameters=[LaunchConfiguration('params_file')], output='screen',
             condition=UnlessCondition(LaunchConfiguration('lifecycle'))),
        # the managed variant, under the plain node's name (the same params file applies);
        # a lifecycle manager configures and activates it (docs/interface.md)
        LifecycleNode(package='stepper_drivers', executable='rd4_lifecycle_node',
                      name='rd4_node', namespace='',
                      parameters=[LaunchConfiguration('params_file')], output='screen',
                      condition=IfCondition(LaunchConfiguration('lifecycle'))),
    ])
