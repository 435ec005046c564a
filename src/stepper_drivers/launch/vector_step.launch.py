"""AEC Vector Step node (CANopen) with its params file; sim:=true also starts the loopback
socketcand broker (127.0.0.1:29536, the port config/vector_step.yaml names) and the simulated
drives on it. On a Linux CAN card pass params_file:=<your file> with can.interface: socketcan
(stepperctl scan vector_step writes one). The simulator and the node connect once the broker
listens (python-can retries for 10 s; the node reconnects anyway).
"""

import os

from ament_index_python.packages import get_package_prefix, get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory('stepper_drivers'), 'config')
    sim = IfCondition(LaunchConfiguration('sim'))
    return LaunchDescription([
        DeclareLaunchArgument('params_file',
                              default_value=os.path.join(config, 'vector_step.yaml')),
        DeclareLaunchArgument('sim', default_value='false',
                              description='also start socketcand_broker and vector_step_sim '
                              '(config/vector_step_sim.yaml)'),
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: the managed (lifecycle) node, '
                              'vector_step_lifecycle_node, waiting for configure and activate'),
        # Not a ROS node (no --ros-args): a plain process.
        ExecuteProcess(cmd=[os.path.join(get_package_prefix('stepper_sim'), 'lib',
                                         'stepper_sim', 'socketcand_broker'),
                            '--port', '29536'], condition=sim, output='screen'),
        Node(package='stepper_sim', executable='vector_step_sim', name='vector_step_sim',
             parameters=[os.path.join(config, 'vector_step_sim.yaml')], condition=sim,
             output='screen'),
        Node(package='stepper_drivers', executable='vector_step_node', name='vector_step_node',
             parameters=[LaunchConfiguration('params_file')], output='screen',
             condition=UnlessCondition(LaunchConfiguration('lifecycle'))),
        # the managed variant, under the plain node's name (the same params file applies);
        # a lifecycle manager configures and activates it (docs/interface.md)
        LifecycleNode(package='stepper_drivers', executable='vector_step_lifecycle_node',
                      name='vector_step_node', namespace='',
                      parameters=[LaunchConfiguration('params_file')], output='screen',
                      condition=IfCondition(LaunchConfiguration('lifecycle'))),
    ])
