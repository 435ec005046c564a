"""R.T.A. X-MIND K node with its params file; sim:=true also starts the simulated drives.

The simulator creates the pty symlink /tmp/xmind_k_sim.tty that config/xmind_k.yaml opens; on a
real line pass params_file:=<your file> with port: /dev/ttyUSB0 (stepperctl scan xmind_k
writes one).
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
        DeclareLaunchArgument('params_file',
                              default_value=os.path.join(config, 'xmind_k.yaml')),
        DeclareLaunchArgument('sim', default_value='false',
                              description='also start xmind_k_sim (config/xmind_k_sim.yaml)'),
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: the managed (lifecycle) node, '
                              'xmind_k_lifecycle_node, waiting for configure and activate'),
        Node(package='stepper_sim', executable='xmind_k_sim', name='xmind_k_sim',
             parameters=[os.path.join(config, 'xmind_k_sim.yaml')],
             condition=IfCondition(LaunchConfiguration('sim')), output='screen'),
        Node(package='stepper_drivers', executable='xmind_k_node', name='xmind_k_node',
             parameters=[LaunchConfiguration('params_file')], output='screen',
             condition=UnlessCondition(LaunchConfiguration('lifecycle'))),
        # the managed variant, under the plain node's name (the same params file applies);
        # a lifecycle manager configures and activates it (docs/interface.md)
        LifecycleNode(package='stepper_drivers', executable='xmind_k_lifecycle_node',
                      name='xmind_k_node', namespace='',
                      parameters=[LaunchConfiguration('params_file')], output='screen',
                      condition=IfCondition(LaunchConfiguration('lifecycle'))),
    ])
