from glob import glob
import os
from os.path import isfile
import runpy

from setuptools import find_packages, setup

package_name = 'stepper_drivers'
HERE = os.path.dirname(os.path.realpath(__file__))
# The vendor table, read as a file: setup.py imports neither the package nor rclpy.
ROWS = runpy.run_path(os.path.join(HERE, 'stepper_drivers', 'vendors', 'table.py'))['ROWS']

# Two console scripts per vendor (<key>_node, <key>_lifecycle_node), both entry_points.main (the
# name it is started under picks the vendor), and stepperctl.
NODES = [n for row in ROWS for n in (row.node, row.lifecycle_node)]

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/config', [f for f in glob('config/*') if isfile(f)]),
        ('share/' + package_name + '/config/moveit', glob('config/moveit/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='stepper_drivers team',
    maintainer_email='dev@stepper-drivers.local',
    description='ROS 2 nodes for four stepper drive product lines',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{n} = stepper_drivers.ros.entry_points:main' for n in NODES]
        + ['stepperctl = stepper_drivers.cli.main:stepperctl'],
    },
)
