"""A benchmark's helper process: the benchmark script run again with a hidden flag (an echo
controller, a publisher), its stdout read by the parent, and nothing of it left running.

No rclpy here.
"""
import contextlib
import json
import os
import signal
import subprocess
import sys
from typing import Iterator, Sequence

from metampc_bringup.orchestration.lifeline import child_env

STOP_S = 5.0    # s for the child to end after SIGINT before SIGKILL


@contextlib.contextmanager
def script_child(script: str, args: Sequence[str], stop_s: float = STOP_S
                 ) -> Iterator[subprocess.Popen]:
    """`python script args...` in a session of its own, stdout piped as text, environment
    inherited; when the block ends with it still running, SIGINT to its process group, then
    SIGKILL after `stop_s` s. The child may hold a lifeline to this process
    (:func:`.lifeline.hold`)."""
    child = subprocess.Popen([sys.executable, script, *args], stdout=subprocess.PIPE,
                             text=True, start_new_session=True, env=child_env())
    try:
        yield child
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGINT)
            try:
                child.wait(stop_s)
            except subprocess.TimeoutExpired:
                os.killpg(child.pid, signal.SIGKILL)
                child.wait()
        child.stdout.close()


def last_json_line(text: str) -> dict:
    """The JSON object on the last line of `text` (ValueError or IndexError if none)."""
    return json.loads(text.strip().splitlines()[-1])
