from setuptools import setup

# Metadata and packages are in setup.cfg; ament's index needs these data files.
NAME = 'metampc_bringup'
setup(data_files=[('share/ament_index/resource_index/packages', ['resource/' + NAME]),
                  ('share/' + NAME, ['package.xml'])])
