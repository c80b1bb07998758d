"""An rclpy node with a context of its own, spun in a background thread.

The orchestrator's client and the tests' probe both are one: the calling thread stays free
to wait on futures and conditions while callbacks run.
"""
import threading
import time
from typing import Any, Callable, List, Optional

import rclpy
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

SPIN_POLL_S = 0.5    # s: the longest a spin waits before it looks at the stop flag again


class SpunNode:
    """`self.node` spun in a daemon thread until :meth:`close`, by a SingleThreadedExecutor
    (threads=1) or a MultiThreadedExecutor."""

    def __init__(self, name: str, threads: int = 1):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.executor = (SingleThreadedExecutor(context=self.context) if threads == 1 else
                         MultiThreadedExecutor(num_threads=threads, context=self.context))
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=SPIN_POLL_S)

    def wait_for(self, predicate: Callable[[], bool], timeout: float, what: str,
                 poll: float = 0.05) -> None:
        """Poll `predicate` until true; AssertionError naming `what` after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')
            time.sleep(poll)

    def call(self, client: Any, request: Any, timeout: float,
             resend_every: Optional[float] = None) -> Any:
        """Call `client`'s service and wait up to `timeout` s for the response.

        `resend_every` (s), for requests that are safe to repeat: send the request again while
        unanswered. rmw_fastrtps drops a response whose writer has not matched the client's
        reader within 100 ms of the send ('failed to send response (timeout): client will not
        receive response'): a first call right after discovery can lose its answer on a
        loaded machine, however long the client waits. Once answered, the match holds.
        """
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            until = deadline if resend_every is None else min(
                deadline, time.monotonic() + resend_every)
            while not future.done() and time.monotonic() < until:
                time.sleep(0.02)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
            if time.monotonic() >= deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for the answer of '
                                     f'{client.srv_name}')

    def node_names(self) -> List[str]:
        return [n for n, _ in self.node.get_node_names_and_namespaces()]

    def wait_for_node(self, name: str, timeout: float = 30.0) -> None:
        self.wait_for(lambda: name in self.node_names(), timeout, f'node {name!r}')

    def close(self) -> None:
        """Stop spinning, then shut the executor down, then destroy the node.

        In that order because rclpy Jazzy's `Executor.shutdown` neither stops a spin in another
        thread nor waits for it: it destroys the executor's guard condition under it (the spin
        thread died in `_wait_for_ready_callbacks` on the None guard), and a node destroyed
        under a spinning executor fails its thread ('cannot use Destroyable because
        destruction was requested', once printed at the Ctrl-C of an experiment)."""
        self._stop.set()
        self.executor.wake()
        self._thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
