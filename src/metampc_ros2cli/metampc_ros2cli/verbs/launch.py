"""`ros2 launch [PKG] FILE [NAME:=VALUE ...]`: the nodes of a YAML launch file
(:mod:`metampc_ros2cli.launch_yaml`), each started as `ros2 run` starts it, until Ctrl-C.

The file is found as ros2launch finds it: a path, or a file of that name under the package's
share folder. Every node is a process of :class:`ProcessGroup` (metampc_bringup): in a session
of its own, its output in a log file of the run's log folder (and on the launcher's, prefixed
`[exec-N]`, with `output: screen`), and holding a lifeline to the launcher, so that nothing
outlives it, SIGKILL included. A node that ends is reported as ros2 launch reports it; Ctrl-C
or SIGTERM stops every node (SIGINT, SIGKILL STOP_S s later) and exits 0; when every node has
ended the launcher exits, 1 if one failed. A file, argument, package or executable that cannot
run is refused with one line and exit status 2 before anything starts.
"""
import datetime
import os
import signal
import socket
import sys
import time
from typing import Any, List


POLL_S = 0.1        # s between two looks at the nodes and their output
STOP_S = 10.0       # s a node may take to stop after its SIGINT before it is killed


def add_parser(subparsers: Any) -> None:
    text = 'Run a launch file'
    p = subparsers.add_parser('launch', help=text, description=text + ' (the YAML format: '
                              'node and arg; docs/nodes.md)')
    p.add_argument('-s', '--show-args', '--show-arguments', action='store_true',
                   help='Show arguments that may be given to the launch file.')
    p.add_argument('package_name', help='Name of the ROS package which contains the launch '
                   'file, or the path of a launch file')
    p.add_argument('launch_file_name', nargs='?', help='Name of the launch file')
    p.add_argument('launch_arguments', nargs='*', help="Arguments to the launch file; "
                   "'<name>:=<value>' (for duplicates, last one wins)")
    p.set_defaults(main=main)


def launch_file(args: Any) -> str:
    """The file the command line names, and its arguments moved into args.launch_arguments
    (ros2launch's rule: a first positional that is a file is the path)."""
    from metampc_ros2cli.launch_yaml import LaunchError
    if os.path.isfile(args.package_name):
        if args.launch_file_name is not None:
            args.launch_arguments.insert(0, args.launch_file_name)
        return args.package_name
    if args.launch_file_name is None:
        raise LaunchError(f"no launch file '{args.package_name}' (give PKG FILE or a path)")
    from ament_index_python.packages import (PackageNotFoundError,
                                             get_package_share_directory)
    try:
        share = get_package_share_directory(args.package_name)
    except PackageNotFoundError:
        raise LaunchError(f"Package '{args.package_name}' not found") from None
    found = [os.path.join(d, args.launch_file_name) for d, _, files in os.walk(share)
             if args.launch_file_name in files]
    if len(found) != 1:
        raise LaunchError(f"file '{args.launch_file_name}' was not found in the share "
                          f"directory of package '{args.package_name}' which is at '{share}'"
                          if not found else f'multiple files named '
                          f"'{args.launch_file_name}' in '{share}': {found}")
    return found[0]


def check_executable(pkg: str, exe: str) -> None:
    """LaunchError unless `ros2 run PKG EXE` has something to run."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    from metampc_ros2cli.launch_yaml import LaunchError
    try:
        prefix = get_package_prefix(pkg)
    except PackageNotFoundError:
        raise LaunchError(f"package '{pkg}' not found") from None
    if not os.access(os.path.join(prefix, 'lib', pkg, exe), os.X_OK):
        raise LaunchError(f"executable '{exe}' not found in package '{pkg}' "
                          f'({os.path.join(prefix, "lib", pkg)})')


def log_folder() -> str:
    """The run's log folder, named and placed as launch's (ROS_LOG_DIR, ROS_HOME/log or
    ~/.ros/log)."""
    base = os.environ.get('ROS_LOG_DIR') or os.path.join(
        os.environ.get('ROS_HOME') or os.path.expanduser('~/.ros'), 'log')
    stamp = datetime.datetime.now().strftime('%Y-%m-%d-%H-%M-%S-%f')
    path = os.path.join(base, f'{stamp}-{socket.gethostname()}-{os.getpid()}')
    os.makedirs(path)
    return path


class Echo:
    """The output of one node so far, read from its log file; whole lines go out prefixed."""

    def __init__(self, path: str, label: str, screen: bool) -> None:
        self.path, self.label, self.screen = path, label, screen
        self.offset, self.partial = 0, ''

    def pump(self, final: bool = False) -> None:
        if not self.screen:
            return
        with open(self.path, errors='replace') as f:
            f.seek(self.offset)
            text = self.partial + f.read()
            self.offset = f.tell()
        lines = text.split('\n')
        self.partial = '' if final else lines.pop()
        for line in lines:
            if line or not final:
                print(f'[{self.label}] {line}')


def _report(label: str, proc: Any, echo: Echo) -> None:
    echo.pump(final=True)
    if proc.returncode == 0:
        print(f'[INFO] [{label}]: process has finished cleanly [pid {proc.pid}]')
    else:
        print(f"[ERROR] [{label}]: process has died [pid {proc.pid}, exit code "
              f"{proc.returncode}, cmd '{' '.join(proc.args)}']; its output: {proc.log_path}")


def main(args: Any) -> int:
    from metampc_ros2cli.launch_yaml import LaunchError, load, nodes, values
    try:
        path = launch_file(args)
        with open(path) as f:
            declared, entries = load(f.read(), path)
        if args.show_args:
            print("Arguments (pass arguments as '<name>:=<value>'):")
            for arg in declared:
                print(f"\n    '{arg.name}':\n        {arg.description or 'no description given'}"
                      + (f"\n        (default: '{arg.default}')" if arg.default is not None
                         else ''))
            return 0
        specs = nodes(entries, values(declared, args.launch_arguments))
        for spec in specs:
            check_executable(spec.pkg, spec.exec)
    except (LaunchError, OSError) as err:
        print(f'ros2 launch: {err}', file=sys.stderr)
        return 2
    return run(specs)


def _terminated(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt('signal SIGTERM')


def run(specs: List[Any]) -> int:
    """Start the nodes, report each end, stop them all on Ctrl-C or SIGTERM."""
    from metampc_bringup.orchestration.processes import ProcessGroup
    signal.signal(signal.SIGTERM, _terminated)      # stops the nodes as Ctrl-C does
    folder = log_folder()
    print(f'[INFO] [launch]: All log files can be found below {folder}')
    group = ProcessGroup(folder)
    running: List[tuple] = []
    failed = False
    try:
        for n, spec in enumerate(specs, 1):
            remaps = dict(spec.remaps)
            if spec.namespace:
                remaps['__ns'] = spec.namespace
            proc = group.start(spec.pkg, spec.exec, params=spec.params, remaps=remaps,
                               name=spec.name)
            label = f'{spec.exec}-{n}'
            running.append((label, proc, Echo(proc.log_path, label, spec.output != 'log')))
            print(f'[INFO] [{label}]: process started with pid [{proc.pid}]')
        while running:
            for entry in list(running):
                label, proc, echo = entry
                echo.pump()
                if proc.poll() is not None:
                    _report(label, proc, echo)
                    failed |= proc.returncode != 0
                    running.remove(entry)
            time.sleep(POLL_S)
        return int(failed)
    except KeyboardInterrupt as stop:
        print('[WARNING] [launch]: ' + (str(stop) or 'user interrupted with ctrl-c (SIGINT)'))
        return 0
    finally:
        for s in (signal.SIGINT, signal.SIGTERM):   # the nodes are being stopped already
            signal.signal(s, signal.SIG_IGN)
        group.stop_all(timeout=STOP_S)
        for label, proc, echo in running:
            _report(label, proc, echo)
