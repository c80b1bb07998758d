"""`ros2 param`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'param', 'Various param related sub-commands')
