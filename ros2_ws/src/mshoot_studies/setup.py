from setuptools import find_packages, setup

package_name = 'mshoot_studies'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        # the mshoot command: a plain script (a console-script entry point's launcher reads
        # the installed packages' metadata first, at every command)
        ('bin', ['scripts/mshoot']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mshoot developers',
    maintainer_email='dev@mshoot.invalid',
    description='Applications of mshoot_core: the reference case and study, sweeps, the '
                'mshoot command.',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
)
