"""The `ros2` shim follows ros2run's lookup rules (checked on a fake ament prefix tree)."""
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

SHIM = pathlib.Path(__file__).resolve().parents[1] / 'scripts' / 'ros2_shim.py'
MARKER = pathlib.Path('share/ament_index/resource_index/packages')

ECHO = '''#!/bin/sh
echo "ran $0 with: $*"
exit ${EXIT_CODE:-0}
'''
TRAP = '''#!/bin/sh
trap 'echo got-sigint; exit 42' INT
echo ready
while true; do sleep 0.05; done
'''


def _package(prefix: pathlib.Path, pkg: str, exes: dict):
    (prefix / MARKER).mkdir(parents=True, exist_ok=True)
    (prefix / MARKER / pkg).write_text('')
    for rel, body in exes.items():
        path = prefix / 'lib' / pkg / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(body)
        path.chmod(0o755)


@pytest.fixture
def tree(tmp_path):
    first, second = tmp_path / 'first', tmp_path / 'second'
    _package(first, 'pkg_a', {'talk': ECHO, 'trap': TRAP})
    (first / 'lib' / 'pkg_a' / 'not_exec').write_text('')
    _package(second, 'pkg_a', {'talk': ECHO, 'only_second': ECHO})
    _package(second, 'pkg_b', {'dup': ECHO, 'sub/dup': ECHO})
    return {'AMENT_PREFIX_PATH': f'{first}{os.pathsep}{second}', 'first': str(first)}


def _ros2(tree, *args, **env):
    return subprocess.run([sys.executable, str(SHIM), *args], capture_output=True, text=True,
                          env={**os.environ, 'AMENT_PREFIX_PATH': tree['AMENT_PREFIX_PATH'],
                               **env}, timeout=30)


def test_first_prefix_wins_and_arguments_pass_through(tree):
    r = _ros2(tree, 'run', 'pkg_a', 'talk', 'x', '--ros-args', '-p', 'dt:=0.05')
    assert r.returncode == 0
    assert r.stdout.strip() == (f"ran {tree['first']}/lib/pkg_a/talk with: "
                                'x --ros-args -p dt:=0.05')


def test_exit_status_passed_back(tree):
    assert _ros2(tree, 'run', 'pkg_a', 'talk', EXIT_CODE='7').returncode == 7


def test_unknown_package(tree):
    r = _ros2(tree, 'run', 'no_such_pkg', 'talk')
    assert r.returncode != 0 and r.stderr.strip() == 'Package not found'


def test_unknown_or_non_executable(tree):
    # only_second exists in the second prefix, but pkg_a resolves to the first one.
    for exe in ('nothing', 'only_second', 'not_exec'):
        r = _ros2(tree, 'run', 'pkg_a', exe)
        assert r.returncode != 0 and r.stderr.strip() == 'No executable found', exe


def test_two_matches(tree):
    r = _ros2(tree, 'run', 'pkg_b', 'dup')
    assert r.returncode != 0 and r.stderr.startswith('Multiple executables found')
    assert r.stderr.count('/dup') == 2


def test_sigint_forwarded(tree):
    proc = subprocess.Popen([sys.executable, str(SHIM), 'run', 'pkg_a', 'trap'],
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, 'AMENT_PREFIX_PATH': tree['AMENT_PREFIX_PATH']})
    try:
        assert proc.stdout.readline().strip() == 'ready'
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(10) == 42
        assert 'got-sigint' in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_pkg_verbs(tree):
    assert _ros2(tree, 'pkg', 'list').stdout.split() == ['pkg_a', 'pkg_b']
    lines = _ros2(tree, 'pkg', 'executables', 'pkg_a').stdout.splitlines()
    assert lines == ['pkg_a talk', 'pkg_a trap']
    assert _ros2(tree, 'pkg', 'prefix', 'pkg_a').stdout.strip() == tree['first']
    assert _ros2(tree, 'pkg', 'executables', 'nope').returncode != 0


@pytest.mark.parametrize('args', [['pkg', 'create', 'x'], ['pkg'], ['run', 'pkg_a']])
def test_unsupported_run_and_pkg_verbs(tree, args):
    r = _ros2(tree, *args)
    assert r.returncode == 2
    assert 'of run and pkg it has: run, pkg list, pkg executables, pkg prefix' in r.stderr


def test_sigint_before_the_child_starts_ends_the_shim_with_status_0(tree):
    """A signal noted while the shim starts (its handler is installed before its imports):
    the child is never started and the exit status is 0, as for a node stopped by Ctrl-C."""
    script = (f'import runpy, signal, os, sys; sys.argv = ["ros2", "run", "pkg_a", "trap"]; '
              f'g = runpy.run_path({str(SHIM)!r}, run_name="shim"); '
              f'os.kill(os.getpid(), signal.SIGINT); '
              f'sys.exit(g["main"]())')
    result = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                            timeout=30, env={**os.environ,
                                             'AMENT_PREFIX_PATH': tree['AMENT_PREFIX_PATH']})
    assert result.returncode == 0 and not result.stderr, result
    assert 'ready' not in result.stdout, 'the child was not started'


def test_help_lists_every_verb_run_and_pkg_included(tree):
    """`ros2 --help` names the verbs the shim handles itself as well as ros2cli's."""
    out = _ros2(tree, '--help')
    assert out.returncode == 0, out.stderr
    listed = {line.split()[0] for line in out.stdout.splitlines()
              if line.startswith('    ') and line.split()}
    assert {'node', 'topic', 'service', 'param', 'interface', 'bag', 'pkg', 'run'} <= listed


def test_fix_cmake_paths_help_prints_usage_and_changes_nothing(tmp_path):
    script = SHIM.parent / 'fix_cmake_paths.py'
    out = subprocess.run([sys.executable, str(script), '--help'], capture_output=True,
                         text=True, timeout=30)
    assert out.returncode == 0 and out.stdout.startswith('usage: fix_cmake_paths.py')
    assert 'rewrote' not in out.stdout
    out = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True,
                         text=True, timeout=30)
    assert out.returncode == 2 and 'has no share/ folder' in out.stderr
