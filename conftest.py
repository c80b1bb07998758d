"""Session-wide test isolation: a ROS domain of our own, discovery on localhost only.

The domain id is claimed with an exclusive lock file, so concurrent test sessions on one
machine never share a domain; every process a test starts inherits the environment.
"""
import fcntl
import os
import tempfile

import pytest

_lock = None


def _claim_domain() -> int:
    global _lock
    for domain in range(1, 102):
        path = os.path.join(tempfile.gettempdir(), f'metampc-ros-domain-{domain}.lock')
        handle = open(path, 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _lock = handle  # held until the session ends
        return domain
    raise RuntimeError('no free ROS_DOMAIN_ID in 1..101 for this test session')


def pytest_configure(config):
    os.environ['ROS_DOMAIN_ID'] = str(_claim_domain())
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_LOCALHOST_ONLY', None)


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
