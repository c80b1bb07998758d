from setuptools import find_packages, setup

package_name = 'metampc_controller'

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
    description='Neural state-space model and latent linear MPC: cores and the controller node.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'controller = metampc_controller.controller_node:main',
        ],
    },
)
