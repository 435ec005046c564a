from glob import glob

from setuptools import find_packages, setup

package_name = 'stepper_drivers'

# One line per vendor node: '<exe> = stepper_drivers.entry_points:<function>'.
NODES = ['xplus_mt_node', 'xmind_k_node', 'rd4_node', 'vector_step_node', 'socketcand_broker',
         'stepperctl']

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/config', glob('config/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='stepper_drivers team',
    maintainer_email='dev@stepper-drivers.local',
    description='ROS 2 nodes for four stepper drive product lines',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{n} = stepper_drivers.entry_points:{n}' for n in NODES],
    },
)
