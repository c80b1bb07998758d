from setuptools import find_packages, setup

package_name = 'metampc_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='metampc developers',
    maintainer_email='metampc@example.com',
    description='Recorder, orchestration and MCAP analysis of metampc runs.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'recorder = metampc_bringup.recorder_node:main',
        ],
    },
)
