"""`ros2 bag`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'bag', 'Various bag related sub-commands')
