from setuptools import setup

# Metadata, packages and entry points are in setup.cfg; ament's index needs these data files.
NAME = 'metampc_model'
setup(data_files=[('share/ament_index/resource_index/packages', ['resource/' + NAME]),
                  ('share/' + NAME, ['package.xml'])])
