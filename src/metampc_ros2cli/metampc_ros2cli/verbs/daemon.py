"""`ros2 daemon start|stop|status`, as ros2cli's (metampc_ros2cli.daemon)."""
from typing import Any

from metampc_ros2cli import daemon
from metampc_ros2cli.cli import add_family


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'daemon', 'Various daemon related sub-commands')
    verbs.add_parser('start', help='Start the daemon if it isn\'t running').set_defaults(
        main=start)
    verbs.add_parser('stop', help='Stop the daemon if it is running').set_defaults(main=stop)
    verbs.add_parser('status', help='Output the status of the daemon').set_defaults(
        main=status)


def start(args: Any) -> int:
    print('The daemon has been started' if daemon.start() else 'The daemon is already running')
    return 0


def stop(args: Any) -> int:
    print('The daemon has been stopped' if daemon.stop() else 'The daemon is not running')
    return 0


def status(args: Any) -> int:
    print('The daemon is running' if daemon.running() else 'The daemon is not running')
    return 0
