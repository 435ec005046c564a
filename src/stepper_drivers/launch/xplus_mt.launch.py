"""R.T.A. X-PLUS MT node with its params file; sim:=true also starts the simulated drives."""

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
        DeclareLaunchArgument('params_file', default_value=os.path.join(config, 'xplus_mt.yaml')),
        DeclareLaunchArgument('sim', default_value='false',
                              description='also start xplus_mt_sim (config/xplus_mt_sim.yaml)'),
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: the managed (lifecycle) node, '
                              'xplus_mt_lifecycle_node, waiting for configure and activate'),
        Node(package='stepper_sim', executable='xplus_mt_sim', name='xplus_mt_sim',
             parameters=[os.path.join(config, 'xplus_mt_sim.yaml')],
             condition=IfCondition(LaunchConfiguration('sim')), output='screen'),
        Node(package='stepper_drivers', executable='xplus_mt_node', name='xplus_mt_node',
             parameters=[LaunchConfiguration('params_file')], output='screen',
             condition=UnlessCondition(LaunchConfiguration('lifecycle'))),
        # the managed variant, under the plain node's name (the same params file applies);
        # a lifecycle manager configures and activates it (docs/interface.md)
        LifecycleNode(package='stepper_drivers', executable='xplus_mt_lifecycle_node',
                      name='xplus_mt_node', namespace='',
                      parameters=[LaunchConfiguration('params_file')], output='screen',
                      condition=IfCondition(LaunchConfiguration('lifecycle'))),
    ])
