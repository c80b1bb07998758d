"""Start ROS 2 nodes as processes with `ros2 run` semantics, and stop every one of them.

Used by the orchestrator and by the tests. Each node starts in a session of its own (`ros2 run`
then puts the node in a process group of its own inside it), so a SIGINT to the session's
leader reaches the node once, and SIGKILL can reach every process of the session. Each node
dies with the process that started it (:mod:`.lifeline`), whatever killed that, and holds that
process's ROS domain claimed until it has ended (:func:`.domain.held_fds`).
No rclpy here.
"""
import contextlib
import os
import signal
import subprocess
import threading
import time
from typing import Dict, Iterable, Iterator, List, Optional, Union

from metampc_bringup.orchestration.domain import held_fds
from metampc_bringup.orchestration.lifeline import child_env
from metampc_common.ros_args import ros_args

STACK_DUMP_S = 2.0    # s for a hung node to write its thread stacks (SIGUSR1) before SIGKILL
LOG_TAIL = 6000       # characters of a hung node's output in the error


def session_pids(leader: Union[subprocess.Popen, int]) -> List[int]:
    """Pids of every live process in the session that `leader` (a process we started with
    start_new_session, or its pid) leads: a `ros2 run` and the node it started.

    Once a Popen leader is reaped, its pid may belong to a new process (pid numbers wrap at
    /proc/sys/kernel/pid_max, 32768 here, and a suite's threads use them up): the kernel keeps
    a session's number while any member lives, so a live process with that pid means none of
    ours is left, and the session of that number is somebody else's.
    """
    sid = leader if isinstance(leader, int) else leader.pid
    if not isinstance(leader, int) and leader.returncode is not None \
            and os.path.exists(f'/proc/{sid}'):
        return []
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


class StopTimeout(subprocess.TimeoutExpired):
    """A process outlived its SIGINT; the message ends with the tail of its output."""

    def __str__(self) -> str:
        return f'{super().__str__()}; its output ends with:\n{self.output or ""}'


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM noted inside the block and raised again, to the handlers of before,
    when it ends (main thread only; elsewhere Python delivers no signal anyway)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: List[int] = []
    before = {s: signal.signal(s, lambda signum, _frame: held.append(signum))
              for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
        for s in held[:1]:
            signal.raise_signal(s)


class ProcessGroup:
    """Nodes started for one run or test; `stop_all` stops every one (SIGINT, then SIGKILL)."""

    def __init__(self, log_dir: str, env: Optional[Dict[str, str]] = None):
        """log_dir: where each process's stdout+stderr go; env: overrides for every process."""
        self.log_dir = log_dir
        self.env = dict(env or {})
        self.procs: List[subprocess.Popen] = []

    def start(self, pkg: str, exe: str, params: Optional[Dict[str, object]] = None,
              remaps: Optional[Dict[str, str]] = None, name: Optional[str] = None,
              extra_args: Optional[List[str]] = None, env: Optional[Dict[str, str]] = None,
              prefix: Iterable[str] = ()) -> subprocess.Popen:
        """Run `[prefix...] ros2 run pkg exe [extra_args] --ros-args ...`; output to a log file.

        prefix: a command to run it under (e.g. `ip netns exec host1`).
        """
        cmd = [*prefix, 'ros2', 'run', pkg, exe, *(extra_args or []),
               *ros_args(params, remaps, name)]
        log_path = os.path.join(self.log_dir, f'{name or exe}-{len(self.procs)}.log')
        # Ctrl-C (or SIGTERM) between the fork and the append would leave a node that
        # stop_all does not know (measured: an experiment interrupted while starting its nodes
        # left a controller running in a domain it no longer held). Such a signal is held and
        # delivered once the process is in the group.
        with signals_held(), open(log_path, 'w') as log:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True,
                                    pass_fds=held_fds(),
                                    env=child_env({**os.environ, **self.env, **(env or {}),
                                                   'PYTHONUNBUFFERED': '1'}))
            proc.log_path = log_path
            self.procs.append(proc)
        return proc

    @staticmethod
    def output(proc: subprocess.Popen) -> str:
        """Everything the process printed so far."""
        with open(proc.log_path) as f:
            return f.read()

    @staticmethod
    def interrupt(proc: subprocess.Popen, timeout: float = 10.0) -> int:
        """SIGINT to the process's group (as Ctrl-C does), wait, return the exit code.

        If it is still running after `timeout` s, the nodes of its session are asked for their
        thread stacks (SIGUSR1: metampc nodes register faulthandler for it), every process of
        the session is killed and :class:`StopTimeout` is raised with the end of the output.
        """
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            # proc itself is the `ros2 run` (no handler: SIGUSR1 would end it); its children
            # are the nodes.
            for pid in session_pids(proc):
                if pid != proc.pid:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGUSR1)
            time.sleep(STACK_DUMP_S)
            ProcessGroup.kill(proc)
            log = getattr(proc, 'log_path', None)
            tail = ProcessGroup.output(proc)[-LOG_TAIL:] if log else ''
            raise StopTimeout(proc.args, timeout, output=tail) from None

    @staticmethod
    def kill(proc: subprocess.Popen) -> None:
        """SIGKILL every process of proc's session (kill -9 of the node and its `ros2 run`).

        The nodes first: killed after their `ros2 run`, a node would get its lifeline's
        SIGTERM first and could still end cleanly (a recorder finishing its file)."""
        pids = session_pids(proc)
        for pid in sorted(pids, key=lambda p: p == proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()

    def stop_all(self, timeout: float = 5.0) -> None:
        """Stop every process started here, newest first; nothing of theirs is left running."""
        for proc in reversed(self.procs):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError, subprocess.TimeoutExpired):
                    self.interrupt(proc, timeout=timeout)
            # Also reaps a node left behind by a `ros2 run` that died first.
            if proc.poll() is None or session_pids(proc):
                self.kill(proc)
