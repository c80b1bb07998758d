"""The plant families this project ships (registered in setup.cfg, group metampc.plant_families).

Each module holds one family: its equations in the docstring (as in docs/families.md), its
components with units, its prior Theta and its defaults.
"""
