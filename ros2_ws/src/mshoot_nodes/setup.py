from glob import glob

from setuptools import find_packages, setup

package_name = 'mshoot_nodes'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mshoot developers',
    maintainer_email='dev@mshoot.invalid',
    description='ROS 2 nodes of mshoot: emulator, forecaster, MPC, bag tools.',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'emulator = mshoot_nodes.emulator_node:main',
            'forecaster = mshoot_nodes.forecaster_node:main',
            'mpc = mshoot_nodes.mpc_node:main',
            'recorder = mshoot_nodes.recorder_node:main',
            'replayer = mshoot_nodes.replayer_node:main',
            'rule = mshoot_nodes.rule_node:main',
            'boptest = mshoot_nodes.boptest_run:main',
            'bringup = mshoot_nodes.bringup:main',
            'bringup_processes = mshoot_nodes.processes:main',
        ],
    },
)
