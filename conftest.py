"""Session-wide test isolation: a ROS domain of our own, discovery on localhost only; and no
process left running after the suite.

The domain id is claimed with an exclusive lock file, so concurrent test sessions on one
machine never share a domain; every process a test starts inherits the environment, with
METAMPC_TEST_SESSION=<this pytest's pid>. When the session ends, a process that still holds
that variable (whatever started it, wherever it was re-parented) 5 s later is an orphan: it
is named, killed, and the session fails.

`make test` runs the suite on two pytest-xdist workers (`--dist loadgroup`): each worker is a
session of its own (its own domain, its own orphan check). A test file is one group, so its
module fixtures are built once; files that share a session fixture name one group with
`pytestmark = pytest.mark.xdist_group(NAME)`.
"""
import os
import signal
import time

import pytest

from metampc_testing import SESSION_ENV

# The recorder fixtures and the session's one recorded closed-loop run, for the recording and the
# bringup tests alike (test/ is on pythonpath); the joint robot's recording and a meta-model, for
# adaptation from a recording.
pytest_plugins = ['recording_fixtures', 'robot_recording']

ORPHAN_GRACE_S = 5.0    # the bound: nothing of a stopped run left 5 s later


def pytest_configure(config):
    from metampc_bringup.orchestration.domain import isolate
    if hasattr(config, 'workerinput'):
        # An xdist worker dies with the pytest that started it (SIGKILL of that one left a
        # worker running its test, and the test's nodes with it); the processes it starts die
        # with it in turn (their lifelines). Its SESSION_ENV is still that pytest's pid here.
        from metampc_bringup.orchestration.lifeline import parent_death_signal
        parent_death_signal(signal.SIGKILL, int(os.environ[SESSION_ENV]))
    isolate('LOCALHOST')
    os.environ[SESSION_ENV] = str(os.getpid())
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # Started in the background of a non-interactive shell (`make test &`), the session
        # inherits SIGINT ignored, and so would every process it starts until a test installs
        # a handler: a child that relies on Python's own Ctrl-C handling then outlives the
        # SIGINT that stops it (test_script_child failed so, depending on the test order).
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.hookimpl(tryfirst=True)    # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker('xdist_group') is None:
            item.add_marker(pytest.mark.xdist_group(item.path.name))
    if getattr(config.option, 'loadgroup', False) and items and hasattr(items[0], '_id'):
        for item in items:
            _tag_group(item)


def _tag_group(item) -> None:
    """Append '@<group>' to the item's node id, as xdist does for --dist loadgroup: xdist 3.8
    writes it to ``item._nodeid``, which pytest 9.2 no longer reads (the id is ``item._id``),
    so without this no test was grouped (a group's fixtures were built on both workers)."""
    from _pytest.nodeid import NodeId
    names = sorted({str(m.args[0] if m.args else m.kwargs.get('name', 'default'))
                    for m in item.iter_markers('xdist_group')})
    item._id = NodeId.parse(f'{item.nodeid}@{"_".join(names)}')


def _left_running() -> list:
    """Processes this session started, directly or not, that still run; not this one, nor
    the multiprocessing resource tracker a pool of this process started (it ends with it)."""
    from metampc_bringup.orchestration.procfs import pids_with_env
    me = os.getpid()
    left = []
    for pid in pids_with_env({SESSION_ENV: str(me)}):
        try:
            with open(f'/proc/{pid}/cmdline', 'rb') as f:
                cmd = f.read().replace(b'\0', b' ').decode(errors='replace').strip()
            with open(f'/proc/{pid}/stat') as f:
                parent = int(f.read().rsplit(')', 1)[1].split()[1])
        except OSError:
            continue
        if pid != me and not (parent == me and 'multiprocessing.resource_tracker' in cmd):
            left.append((pid, cmd))
    return left


def _stop_daemons() -> None:
    """The `ros2` daemons this session's verbs started (they outlive a verb by design, as
    ros2cli's): stopped as `ros2 daemon stop` does, before the orphan check."""
    from metampc_bringup.orchestration.procfs import pids_with_env
    for pid in pids_with_env({SESSION_ENV: str(os.getpid())}):
        try:
            with open(f'/proc/{pid}/cmdline', 'rb') as f:
                if b'metampc_ros2cli.daemon' in f.read():
                    os.kill(pid, signal.SIGTERM)
        except OSError:
            continue


def pytest_sessionfinish(session, exitstatus):
    _stop_daemons()
    deadline = time.monotonic() + ORPHAN_GRACE_S
    while (left := _left_running()) and time.monotonic() < deadline:
        time.sleep(0.1)
    if not left:
        return
    reporter = session.config.pluginmanager.get_plugin('terminalreporter')
    for pid, cmd in left:
        if reporter:
            reporter.write_line(f'ORPHAN left running after the suite: pid {pid}: {cmd[:200]}',
                                red=True)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_report_header(config):
    return f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID')} (discovery: localhost)"


@pytest.fixture
def procs(tmp_path):
    """A ProcessGroup (metampc_testing) whose processes are all stopped when the test ends."""
    from metampc_testing import ProcessGroup
    group = ProcessGroup(str(tmp_path))
    yield group
    group.stop_all()


@pytest.fixture
def probe():
    """A TestNode (metampc_testing) in the session's isolated domain, closed after the test."""
    from metampc_testing import TestNode
    node = TestNode()
    yield node
    node.close()
