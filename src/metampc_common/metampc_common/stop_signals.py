"""Ctrl-C and SIGTERM for :func:`metampc_common.node_main.run_node`: the spin ends between two
callbacks, and the node is gone before its context is shut down.

rclpy's own handler shuts the context down the moment the signal arrives, so a callback
publishing then fails. Here the first signal is only noted (Python's handler, main thread) and
the executor woken (``signal.set_wakeup_fd``, a thread that calls its ``wake()``); run_node's
loop ends after the callback in progress. A second signal shuts the context down at once,
rclpy's way: the way out of a callback that waits. Why and what failed before:
docs/nodes.md.
"""
import os
import signal
import threading
from typing import Optional

import rclpy

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """SIGINT and SIGTERM handlers, for the rest of the process; main thread only.

    Attributes:
        count: signals received so far.
    """

    def __init__(self):
        self.count = 0
        for signum in SIGNALS:
            signal.signal(signum, self._on_signal)
        self._pipe_w: Optional[int] = None
        self._watcher: Optional[threading.Thread] = None

    @property
    def requested(self) -> bool:
        """Whether a stop was asked for."""
        return self.count > 0

    def _on_signal(self, signum, frame) -> None:
        self.count += 1
        if self.count > 1:
            rclpy.try_shutdown()

    def wake_on_signal(self, executor) -> None:
        """From now on, a signal also wakes `executor` (an rclpy Executor or EventsExecutor)."""
        read_fd, self._pipe_w = os.pipe()
        os.set_blocking(self._pipe_w, False)
        signal.set_wakeup_fd(self._pipe_w, warn_on_full_buffer=False)
        self._watcher = threading.Thread(target=self._watch, args=(read_fd, executor),
                                         daemon=True)
        self._watcher.start()

    @staticmethod
    def _watch(read_fd: int, executor) -> None:
        while os.read(read_fd, 64):     # b'': close() closed the write end
            executor.wake()
        os.close(read_fd)

    def close(self) -> None:
        """Stop waking the executor (before it is shut down); signals are still noted."""
        if self._pipe_w is not None:
            signal.set_wakeup_fd(-1)
            os.close(self._pipe_w)
            self._watcher.join()
            self._pipe_w = self._watcher = None
