"""`ros2 node`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'node', 'Various node related sub-commands')
