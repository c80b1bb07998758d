"""Calls that are safe to repeat: a state-changing request carries an id, and a repeated id is
answered with the first answer, never run twice.

rmw_fastrtps can drop the answer of a first call right after discovery, so the caller resends
with the same id while unanswered; the server keeps the answers of the last ``keep`` ids, a
repeat that comes while the first call still runs waits for its answer, and an empty id runs
every time (a `ros2 service call` by hand). Pure Python: the future type is the node's
(rclpy.task.Future, awaitable in its coroutines). See docs/nodes.md#calls-that-are-safe-to-repeat.
"""
from collections import OrderedDict
from typing import Any, Awaitable, Callable, Tuple

KEEP = 256      # answers kept: far more than one run's calls of any service


class Replies:
    """The answers of one node's state-changing services, by request id."""

    def __init__(self, make_future: Callable[[], Any], keep: int = KEEP):
        """make_future: a new future (set_result, set_exception, done, result; awaitable for
        :meth:`wrap_async`)."""
        self._make_future = make_future
        self._keep = keep
        self._answers: 'OrderedDict[str, Any]' = OrderedDict()
        self.repeats = 0    # repeated ids answered from the first answer

    def claim(self, request_id: str) -> Tuple[bool, Any]:
        """(True, future) the first time an id is seen: run the request and settle the future;
        (False, the first call's future) for a repeat."""
        if request_id in self._answers:
            self.repeats += 1
            return False, self._answers[request_id]
        future = self._make_future()
        self._answers[request_id] = future
        while len(self._answers) > self._keep:
            self._answers.popitem(last=False)
        return True, future

    def wrap(self, handler: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        """A service callback (request, response) -> response that answers a repeated id with
        the first answer. For callbacks that never overlap (one thread or a mutually
        exclusive group): the first call has always ended when a repeat comes."""
        def callback(request: Any, response: Any) -> Any:
            if not request.request_id:
                return handler(request, response)
            first, future = self.claim(request.request_id)
            if not first:
                return future.result()
            try:
                answer = handler(request, response)
            except BaseException as err:
                future.set_exception(err)
                raise
            future.set_result(answer)
            return answer
        return callback

    def wrap_async(self, handler: Callable[[Any, Any], Awaitable[Any]]
                   ) -> Callable[[Any, Any], Awaitable[Any]]:
        """:meth:`wrap` for a coroutine callback, which may overlap with its repeat: the
        repeat awaits the first call's answer."""
        async def callback(request: Any, response: Any) -> Any:
            if not request.request_id:
                return await handler(request, response)
            first, future = self.claim(request.request_id)
            if not first:
                return await future
            try:
                answer = await handler(request, response)
            except BaseException as err:
                future.set_exception(err)
                raise
            future.set_result(answer)
            return answer
        return callback
