from setuptools import setup

# Metadata, packages and entry points are in setup.cfg; ament's index needs these data files,
# and Foxglove's layout goes with them (docs/foxglove.md).
NAME = 'metampc_recording'
setup(data_files=[('share/ament_index/resource_index/packages', ['resource/' + NAME]),
                  ('share/' + NAME, ['package.xml']),
                  ('share/' + NAME + '/foxglove', ['foxglove/metampc_layout.json'])])
