from glob import glob

from setuptools import setup

# Metadata and packages are in setup.cfg; ament's index needs these data files, and `ros2
# launch metampc_bringup FILE` finds FILE under share/metampc_bringup.
NAME = 'metampc_bringup'
setup(data_files=[('share/ament_index/resource_index/packages', ['resource/' + NAME]),
                  ('share/' + NAME, ['package.xml']),
                  ('share/' + NAME + '/launch', glob('launch/*.launch.yaml'))])
