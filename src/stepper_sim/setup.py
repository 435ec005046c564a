from glob import glob

from setuptools import find_packages, setup

package_name = 'stepper_sim'

# One line per simulator: '<exe> = stepper_sim.<module>:main'.
SIMS = {'xplus_mt_sim': 'stepper_sim.xplus_mt_sim:main',
        'rd4_sim': 'stepper_sim.rd4_sim:main',
        'xmind_k_sim': 'stepper_sim.xmind_k_sim:main',
        'vector_step_sim': 'stepper_sim.vector_step_sim:main'}

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
