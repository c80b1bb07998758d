"""A process that dies with whoever started it, whatever killed that (SIGKILL included).

The kernel's parent-death signal (prctl PR_SET_PDEATHSIG, Linux): a spawner puts its own pid
in the child's environment (:func:`child_env`); the child asks for the signal at its start
(:func:`hold`) and, when its parent is already gone by then, sends it to itself at once. The
`ros2` shim holds one and gives its node one, so a killed orchestrator, seed child or test
ends the nodes too. Spawn from the main thread or a thread that lives as long as the children
("the parent" is the thread that forked). Only processes started with the variable set hold a
lifeline: a node started by hand outlives its shell. Process lifetime: docs/nodes.md. No rclpy
here.
"""
import ctypes
import multiprocessing
import os
import signal
import sys
from typing import Dict, Mapping, Optional

ENV = 'METAMPC_LIFELINE'    # the pid of the process that started this one
PR_SET_PDEATHSIG = 1        # <linux/prctl.h>
# Loaded here, not in the call: the call may run between fork and exec.
_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith('linux') else None


def child_env(env: Optional[Mapping[str, str]] = None) -> Dict[str, str]:
    """`env` (default os.environ) with this process named as the parent of the child."""
    return {**(os.environ if env is None else env), ENV: str(os.getpid())}


def parent_death_signal(signum: int, parent: int) -> bool:
    """Ask for `signum` when the parent ends; if the parent is no longer `parent` (it is gone
    already), send `signum` to this process now. False where the kernel has no such call.

    Safe between fork and exec of a single-threaded parent (libc is loaded at import).
    """
    if _LIBC is None:
        return False
    if _LIBC.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), 'prctl(PR_SET_PDEATHSIG) failed')
    if os.getppid() != parent:
        os.kill(os.getpid(), signum)
    return True


def hold(signum: int = signal.SIGTERM) -> bool:
    """At a process's start: if a metampc spawner started it (:data:`ENV` set), die by
    `signum` when that spawner ends. Returns whether a lifeline is held."""
    parent = os.environ.get(ENV, '')
    if not parent.isdigit():
        return False
    return parent_death_signal(signum, int(parent))


def hold_in_worker(signum: int = signal.SIGTERM) -> bool:
    """In a multiprocessing worker (a pool's initializer): die by `signum` with the process
    that made the pool. Nothing in the main process."""
    parent = multiprocessing.parent_process()
    return parent is not None and parent_death_signal(signum, parent.pid)
