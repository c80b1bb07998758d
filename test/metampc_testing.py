"""Shared helpers for tests that start real ROS 2 processes.

Every process is started through `ros2 run` (the shim or a real ros2) in the test session's
isolated domain (see conftest.py) and is stopped by the test that started it: use the ``procs``
fixture (a metampc_bringup.orchestration.processes.ProcessGroup).
"""
import json
from pathlib import Path

from metampc_bringup.orchestration.processes import ProcessGroup, session_pids  # noqa: F401
from metampc_bringup.orchestration.spun_node import SpunNode
from rosbags.highlevel import AnyReader

# Set by conftest to the pid of the test session (an xdist worker, or pytest) and inherited by
# every process the session starts: the session's orphan check, and tests that tell their own
# processes from another session's, look for it.
SESSION_ENV = 'METAMPC_TEST_SESSION'


def alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie does not)."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def own_lines(text: str) -> list:
    """The non-empty lines of a process's output, without Fast DDS's shared-memory port
    error: when many participants start at once its port mutex times out (after 2 s,
    eProsima/Fast-DDS#6117) and it logs 'RTPS_TRANSPORT_SHM Error ... Failed init_port', then
    goes on with another port. Seen with 14 plants started together on an idle CI machine;
    not a line of ours."""
    return [line for line in text.splitlines() if line.strip()
            and not ('RTPS_TRANSPORT_SHM' in line and 'Failed init_port' in line)]


class TestNode(SpunNode):
    """An rclpy node spun in a background thread, for probing the graph from a test."""

    __test__ = False    # not a test class, though imported into test modules

    def __init__(self, name: str = 'metampc_test_probe'):
        super().__init__(name)


def read_with_rosbags(mcap_path: str):
    """Events and closed-loop messages of a recording, decoded by rosbags."""
    events, outputs, statuses, inputs = [], [], [], []
    with AnyReader([Path(mcap_path)]) as reader:     # types from the schemas in the file
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            name = conn.topic.rsplit('/', 1)[-1]
            if name == 'experiment_events':
                events.append(json.loads(msg.data))
            elif name in ('y', 'mpc_status', 'u'):
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                {'y': outputs, 'mpc_status': statuses, 'u': inputs}[name].append((stamp, msg))
    return events, outputs, statuses, inputs
