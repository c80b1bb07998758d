#!/usr/bin/env python3
"""A minimal `ros2` command for machines without ros2cli (ROS 2 Jazzy from PyPI wheels).

Verbs handled here (semantics of ros2run / ros2pkg, Jazzy):
  ros2 run PKG EXE [args...]      run an executable of a package, arguments passed through
  ros2 pkg list                   every package on AMENT_PREFIX_PATH
  ros2 pkg executables [PKG]      'PKG EXE' lines, for one package or all
  ros2 pkg prefix PKG             the install prefix of a package
Every other verb (node, topic, service, param, interface, bag, daemon, launch) is the package
metampc_ros2cli (`ros2 -h` lists them), imported only then so that `ros2 run` starts as fast as
before.

Lookup rules (as ros2run): the package's prefix is the first entry of AMENT_PREFIX_PATH that has
share/ament_index/resource_index/packages/PKG; the executable is the one file named EXE that is
executable under <prefix>/lib/PKG (searched recursively). The exit status of the child is passed
back. The child runs in a process group of its own and the shim forwards SIGINT and SIGTERM to
it, so Ctrl-C (or a signal to the shim's process group) reaches the node exactly once; rclpy
nodes treat a second SIGINT during shutdown as an error. A SIGINT or SIGTERM that comes before
the child started ends the shim without starting it (exit status 0, as a node stopped by Ctrl-C).
Lifetime (metampc_bringup.orchestration.lifeline): the node gets SIGTERM when the shim dies,
and a shim started by a metampc spawner gets SIGTERM when that spawner dies, SIGKILL included;
it passes it on to the node and SIGKILLs the node ORPHAN_GRACE_S later if it still runs.
"""
import signal

# Before anything else: a Ctrl-C while the shim starts is noted, not a KeyboardInterrupt.
PENDING = []
CHILD = []


ORPHAN_GRACE_S = 2.0    # s a node whose run was killed may take to stop before SIGKILL


def forward(signum, _frame):
    """Pass a signal on to the child's process group once it runs; note it before. A SIGTERM
    from the lifeline (the spawner is gone): SIGKILL follows after ORPHAN_GRACE_S, so that
    nothing of a killed run outlives it by more than a few seconds, however loaded the
    machine."""
    if CHILD and CHILD[0].poll() is None:
        os.killpg(CHILD[0].pid, signum)
        if signum == signal.SIGTERM and spawner_gone():
            signal.setitimer(signal.ITIMER_REAL, ORPHAN_GRACE_S)
    elif not CHILD:
        PENDING.append(signum)


def kill_child(_signum, _frame):
    if CHILD and CHILD[0].poll() is None:
        os.killpg(CHILD[0].pid, signal.SIGKILL)


def spawner_gone():
    spawner = os.environ.get(lifeline.ENV, '') if lifeline else ''
    return spawner.isdigit() and os.getppid() != int(spawner)


signal.signal(signal.SIGINT, forward)
signal.signal(signal.SIGTERM, forward)
signal.signal(signal.SIGALRM, kill_child)

import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

try:
    from metampc_bringup.orchestration import lifeline  # noqa: E402
except ImportError:     # the workspace is not built: no package to run either
    lifeline = None

MARKER = os.path.join('share', 'ament_index', 'resource_index', 'packages')
SUPPORTED = 'run, pkg list, pkg executables, pkg prefix'


def prefixes():
    return [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


def package_prefix(pkg):
    for prefix in prefixes():
        if os.path.isfile(os.path.join(prefix, MARKER, pkg)):
            return prefix
    return None


def all_packages():
    found = set()
    for prefix in prefixes():
        d = os.path.join(prefix, MARKER)
        if os.path.isdir(d):
            found.update(n for n in os.listdir(d) if not n.startswith('.'))
    return sorted(found)


def executables(prefix, pkg):
    base = os.path.join(prefix, 'lib', pkg)
    paths = []
    for dirpath, dirnames, filenames in os.walk(base):
        dirnames[:] = [d for d in dirnames if not d.startswith('.')]
        for name in filenames:
            path = os.path.join(dirpath, name)
            if os.access(path, os.X_OK):
                paths.append(path)
    return sorted(paths)


def run(pkg, exe, args):
    prefix = package_prefix(pkg)
    if prefix is None:
        print('Package not found', file=sys.stderr)
        return 1
    matches = [p for p in executables(prefix, pkg) if os.path.basename(p) == exe]
    if not matches:
        print('No executable found', file=sys.stderr)
        return 1
    if len(matches) > 1:
        print('Multiple executables found:', file=sys.stderr)
        for m in matches:
            print(f'- {m}', file=sys.stderr)
        return 1
    if PENDING:
        return 0    # stopped before the node started
    shim = os.getpid()
    # The node dies with this shim (and gets the parent-death signal's pid in its
    # environment); the shim's other open files, a ROS domain's lock among them
    # (metampc_bringup.orchestration.domain), go on to the node, so the domain stays claimed
    # until the node has ended.
    proc = subprocess.Popen(
        [matches[0]] + args, process_group=0, close_fds=False,
        env=lifeline.child_env() if lifeline else None,
        preexec_fn=(lambda: lifeline.parent_death_signal(signal.SIGTERM, shim))
        if lifeline else None)
    CHILD.append(proc)
    for signum in PENDING:  # came while Popen forked and exec'd the child
        os.killpg(proc.pid, signum)
    rc = proc.wait()
    # A child killed by a signal: report it as the shell would (128 + signal number).
    return rc if rc >= 0 else 128 - rc


def usage(message):
    print(f'ros2: {message}\nThis ros2 is metampc\'s; of run and pkg it has: {SUPPORTED} '
          '(`ros2 -h` lists the other verbs).\n'
          'usage: ros2 run PKG EXE [args...] | ros2 pkg list | ros2 pkg executables [PKG] | '
          'ros2 pkg prefix PKG', file=sys.stderr)
    return 2


def other_verbs(argv):
    """Every verb but run and pkg: metampc_ros2cli, with Python's own Ctrl-C handling."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if PENDING:
        return 0
    try:
        from metampc_ros2cli.cli import main as cli_main
    except ImportError:
        print('ros2: the package metampc_ros2cli is not on PYTHONPATH; build the workspace '
              '(make build) and source scripts/env.sh', file=sys.stderr)
        return 1
    return cli_main(argv)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if lifeline:
        lifeline.hold()     # started by a metampc spawner: end with it
    if not argv or argv[0] not in ('run', 'pkg'):
        return other_verbs(argv)
    verb, rest = argv[0], argv[1:]
    if verb == 'run':
        if len(rest) < 2:
            return usage('run needs a package and an executable')
        return run(rest[0], rest[1], rest[2:])
    if verb == 'pkg' and rest:
        sub = rest[0]
        if sub == 'list' and len(rest) == 1:
            print('\n'.join(all_packages()))
            return 0
        if sub in ('executables', 'prefix') and len(rest) <= 2:
            pkgs = rest[1:] or ([] if sub == 'prefix' else all_packages())
            if not pkgs:
                return usage('pkg prefix needs a package')
            for pkg in pkgs:
                prefix = package_prefix(pkg)
                if prefix is None:
                    print('Package not found', file=sys.stderr)
                    return 1
                if sub == 'prefix':
                    print(prefix)
                    continue
                for path in executables(prefix, pkg):
                    print(pkg, os.path.basename(path))
            return 0
    return usage(f'unsupported command: {" ".join(argv)}')


if __name__ == '__main__':
    sys.exit(main())
