"""Session-wide test isolation: a ROS domain of our own, discovery on localhost only.

The domain id is claimed with an exclusive lock file, so concurrent test sessions on one
machine never share a domain; every process a test starts inherits the environment.
"""
import os

import pytest


def pytest_configure(config):
    from metampc_bringup.domain import isolate
    isolate('LOCALHOST')


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
