from glob import glob
import os
import runpy

from setuptools import find_packages, setup

package_name = 'stepper_sim'
HERE = os.path.dirname(os.path.realpath(__file__))
# The vendor table of stepper_drivers, read as a file (no import of either package, no rclpy).
ROWS = runpy.run_path(os.path.join(HERE, '..', 'stepper_drivers', 'stepper_drivers', 'vendors',
                                   'table.py'))['ROWS']

# One console script per simulator: '<key>_sim = <row.simulator>', and one per helper a
# simulator needs (row.sim_helpers, e.g. the CAN broker): '<name> = stepper_sim.core.<name>:main'.
SIMS = {row.sim: row.simulator for row in ROWS}
SIMS.update({h: f'stepper_sim.core.{h}:main' for row in ROWS for h, *_args in row.sim_helpers})

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='stepper_drivers team',
    maintainer_email='dev@stepper-drivers.local',
    description='Simulated stepper drives on the real wire protocols',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{exe} = {target}' for exe, target in SIMS.items()],
    },
)
