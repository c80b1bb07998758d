"""`ros2 interface`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'interface', 'Various interface related sub-commands')
