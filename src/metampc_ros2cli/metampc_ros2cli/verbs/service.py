"""`ros2 service`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'service', 'Various service related sub-commands')
