from setuptools import find_packages, setup

package_name = 'mshoot_core'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['fmu_src/*.c', 'fmu_src/*.h', 'fmu_src/*.xml',
                                 'cards/*.yaml', 'mpc_settings/*.yaml', 'schema/*.json',
                                 'boptest/*.json']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mshoot developers',
    maintainer_email='dev@mshoot.invalid',
    description='MPC with multiple shooting for buildings (pure Python core).',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={'console_scripts': []},
)
