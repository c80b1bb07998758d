"""Shared helpers for tests that start real ROS 2 processes.

Every process is started through `ros2 run` (the shim or a real ros2) in the test session's
isolated domain (see conftest.py) and is stopped by the test that started it: use
:func:`ros_processes` as a context manager or the ``procs`` fixture of ``test/conftest.py``.
"""
import contextlib
import os
import signal
import subprocess
import threading
import time
from typing import Callable, Dict, Iterator, List, Optional

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


def ros_args(params: Optional[Dict[str, object]] = None, remaps: Optional[Dict[str, str]] = None,
             name: Optional[str] = None) -> List[str]:
    """Build `--ros-args -p k:=v -r a:=b` arguments; lists become YAML lists."""
    args = ['--ros-args']
    for key, value in (params or {}).items():
        if isinstance(value, bool):
            text = 'true' if value else 'false'
        elif isinstance(value, (list, tuple)):
            text = '[' + ','.join(repr(v) if isinstance(v, str) else str(v) for v in value) + ']'
        else:
            text = str(value)
        args += ['-p', f'{key}:={text}']
    for src, dst in (remaps or {}).items():
        args += ['-r', f'{src}:={dst}']
    if name:
        args += ['-r', f'__node:={name}']
    return args


def session_pids(sid: int) -> List[int]:
    """Pids of every live process in session `sid` (the shim and the node it started)."""
    pids = []
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            with open(f'/proc/{entry}/stat') as f:
                fields = f.read().rsplit(')', 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != 'Z':
            pids.append(int(entry))
    return pids


class ProcessGroup:
    """Processes started by one test; all of them are stopped on exit (SIGINT, then SIGKILL).

    Each process starts in a session of its own; `ros2 run` puts the node in a process group
    of its own inside that session, so SIGKILL goes to every process of the session.
    """

    def __init__(self, log_dir: str):
        self.log_dir = log_dir
        self.procs: List[subprocess.Popen] = []

    def start(self, pkg: str, exe: str, params: Optional[Dict[str, object]] = None,
              remaps: Optional[Dict[str, str]] = None, name: Optional[str] = None,
              extra_args: Optional[List[str]] = None,
              env: Optional[Dict[str, str]] = None) -> subprocess.Popen:
        """`ros2 run pkg exe [extra_args] --ros-args ...`; stdout+stderr go to a log file."""
        cmd = ['ros2', 'run', pkg, exe] + list(extra_args or []) + ros_args(params, remaps, name)
        log_path = os.path.join(self.log_dir, f'{name or exe}-{len(self.procs)}.log')
        log = open(log_path, 'w')
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                env={**os.environ, **(env or {}), 'PYTHONUNBUFFERED': '1'},
                                start_new_session=True)
        proc.log_path = log_path
        log.close()
        self.procs.append(proc)
        return proc

    @staticmethod
    def output(proc: subprocess.Popen) -> str:
        with open(proc.log_path) as f:
            return f.read()

    @staticmethod
    def interrupt(proc: subprocess.Popen, timeout: float = 10.0) -> int:
        """SIGINT to the process group (as Ctrl-C does), wait, return the exit code."""
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            ProcessGroup.kill(proc)
            raise

    @staticmethod
    def kill(proc: subprocess.Popen) -> None:
        """SIGKILL every process of proc's session (kill -9 of the node and its `ros2 run`)."""
        for pid in session_pids(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()

    def stop_all(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError, subprocess.TimeoutExpired):
                    self.interrupt(proc, timeout=5.0)
            # Also reaps a node left behind by a `ros2 run` that died first.
            if proc.poll() is None or session_pids(proc.pid):
                self.kill(proc)


class TestNode:
    """An rclpy node spun in a background thread, for probing the graph from a test."""

    def __init__(self, name: str = 'metampc_test_probe'):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def wait_for(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        """Poll predicate until true; AssertionError naming `what` after timeout seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            time.sleep(0.05)
        raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def node_names(self) -> List[str]:
        return [n for n, _ in self.node.get_node_names_and_namespaces()]

    def wait_for_node(self, name: str, timeout: float = 30.0) -> None:
        self.wait_for(lambda: name in self.node_names(), timeout, f'node {name!r}')

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5.0)


@contextlib.contextmanager
def ros_processes(log_dir: str) -> Iterator[ProcessGroup]:
    group = ProcessGroup(log_dir)
    try:
        yield group
    finally:
        group.stop_all()
