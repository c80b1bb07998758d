"""`ros2 topic`: not written yet."""
from metampc_ros2cli.cli import add_family


def add_parser(subparsers):
    add_family(subparsers, 'topic', 'Various topic related sub-commands')
