"""`ros2 VERB ...`: the verb families of :data:`VERBS`, parsed as ros2cli parses them.

Each module of :mod:`metampc_ros2cli.verbs` adds its family with ``add_parser(subparsers)``;
every sub-verb sets ``main(args) -> int | str`` as its default. As in ros2cli, a string is an
error line (so is a RuntimeError's text): it goes to stderr and the exit status is 1;
argparse's own errors exit with 2, and
Ctrl-C ends a verb (echo, hz, bag play...) with status 0 and no traceback.
"""
import argparse
import importlib
import os
import sys
from typing import Any, List, Optional

VERBS = ('node', 'topic', 'service', 'param', 'interface', 'bag', 'daemon', 'launch')
# Handled by the `ros2` command itself before this module is imported (fast start of a node).
SHIM_VERBS = {'pkg': 'Various package related sub-commands (list, executables, prefix)',
              'run': 'Run a package specific executable'}


def add_family(subparsers: Any, name: str, help: str) -> Any:
    """The parser of verb family `name` (``ros2 NAME``); returns the subparsers of its verbs,
    to each of which a module adds ``set_defaults(main=...)``."""
    family = subparsers.add_parser(name, help=help, description=help)
    family.set_defaults(family_parser=family)
    return family.add_subparsers(title='Commands', dest=f'_{name}_verb',
                                 metavar=f'Call `ros2 {name} <command> -h` for more detailed '
                                 'usage.')


def parser() -> argparse.ArgumentParser:
    """The `ros2` parser with every verb family of :data:`VERBS`."""
    top = argparse.ArgumentParser(
        prog='ros2', description='ros2 is an extensible command-line tool for ROS 2 '
        "(metampc's ros2cli for the pip-installed ROS; `ros2 run` and `ros2 pkg` too).")
    families = top.add_subparsers(title='Commands', dest='_command', metavar='Call `ros2 '
                                  '<command> -h` for more detailed usage.')
    for name in VERBS:
        importlib.import_module(f'metampc_ros2cli.verbs.{name}').add_parser(families)
    for name, text in SHIM_VERBS.items():   # listed in the help; the `ros2` command runs them
        families.add_parser(name, help=text, description=text).set_defaults(
            main=lambda args: f'ros2 {args._command}: run it through the `ros2` command '
                              '(scripts/ros2_shim.py), not this module')
    return top


def main(argv: Optional[List[str]] = None) -> int:
    """Run one `ros2` command line (without the leading 'ros2'); its exit status."""
    top = parser()
    args = top.parse_args(argv)
    handler = getattr(args, 'main', None)
    if handler is None:     # a family without its verb: its help, as ros2cli
        (getattr(args, 'family_parser', None) or top).print_help()
        return 0
    try:
        sys.stdout.reconfigure(line_buffering=True)
    except AttributeError:
        pass
    try:
        rc = handler(args)
    except KeyboardInterrupt:
        return 0
    except RuntimeError as err:     # ros2cli prints these as the error line
        rc = str(err)
    except BrokenPipeError:         # `ros2 ... | head`: the reader has gone, nothing to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if isinstance(rc, str):
        print(rc, file=sys.stderr)
        return 1
    return int(rc or 0)


if __name__ == '__main__':
    sys.exit(main())
