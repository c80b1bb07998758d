"""One training job at a time: the busy rule, the job's latest progress, cancellation.

The learner node runs ``meta_train`` and ``adapt`` in the service callback itself, in a
reentrant callback group of a MultiThreadedExecutor, so a second request is served by another
thread while the first trains. Both services go through one :class:`JobSlot`: a request that
cannot :meth:`JobSlot.claim` it is answered 'busy' at once. The training core reports every
step to :meth:`JobSlot.report` (a ``ProgressFn``), which keeps the latest report for the
``progress`` heartbeat and raises :class:`JobCancelled` once :meth:`JobSlot.cancel` was called
(the node cancels when it shuts down, so a long job does not hold the process). No rclpy.
"""
import threading
import time
from dataclasses import dataclass, replace
from typing import Optional

from metampc_learner.progress import Progress


class JobCancelled(RuntimeError):
    """The job was cancelled (the node is shutting down)."""


@dataclass
class JobStatus:
    """What TrainingProgress carries about a job.

    Attributes:
        phase: 'meta_train' or 'adapt' while it runs; 'done' or 'failed' once it has ended.
        method: the training method.
        progress: the latest report (iteration 0 before the first step); its elapsed is the
            wall time since the job started, s, at the time of the :meth:`JobSlot.current`
            call.
    """

    phase: str
    method: str
    progress: Progress


class JobSlot:
    """Holds at most one running job (thread-safe); see the module docstring."""

    def __init__(self):
        self._lock = threading.Lock()
        self._claimed = False
        self._status: Optional[JobStatus] = None
        self._started = 0.0
        self._cancel = threading.Event()
        self._idle = threading.Event()
        self._idle.set()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def claim(self) -> bool:
        """Take the slot if it is free (True), else False: the caller answers 'busy'."""
        with self._lock:
            if self._claimed or self.cancelled:
                return False
            self._claimed, self._status = True, None
            self._idle.clear()
            return True

    def claim_after(self, phase: str, timeout: float) -> bool:
        """Take the slot (True); if a job of `phase` holds it (or one is being set up), wait
        for it to end, up to `timeout` s. False when another job holds it, or after the wait:
        the caller answers 'busy'."""
        deadline = time.monotonic() + timeout
        while not self.claim():
            status = self.current()
            if (status is not None and status.phase != phase) or self.cancelled:
                return False
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self._idle.wait(min(left, 0.1))
        return True

    def describe(self, phase: str, method: str, total: int) -> JobStatus:
        """Start the clock of the claimed job; its status at iteration 0."""
        with self._lock:
            self._started = time.monotonic()
            self._status = JobStatus(phase, method, Progress(0, total, float('nan'), 0.0))
            return self._status

    def report(self, progress: Progress) -> None:
        """The core's progress callback; raises JobCancelled after :meth:`cancel`."""
        if self.cancelled:
            raise JobCancelled('cancelled: the learner is shutting down')
        with self._lock:
            if self._status is not None:
                self._status = replace(self._status, progress=progress)

    def current(self) -> Optional[JobStatus]:
        """The running job's status with elapsed = now - start, or None when idle."""
        with self._lock:
            if not self._claimed or self._status is None:
                return None
            return replace(self._status, progress=replace(
                self._status.progress, elapsed=time.monotonic() - self._started))

    def busy_reason(self) -> str:
        """'busy: <phase> (<method>) at step i/n' for the answer to a refused request."""
        status = self.current()
        if status is None:
            return 'busy: another request is being set up'
        p = status.progress
        return (f'busy: {status.phase} ({status.method}) running, step {p.iteration}/{p.total}, '
                f'{p.elapsed:.1f} s')

    def release(self, ok: bool) -> Optional[JobStatus]:
        """Free the slot; the final status ('done' or 'failed'), None if never described."""
        with self._lock:
            final = None
            if self._status is not None:
                final = replace(self._status, phase='done' if ok else 'failed',
                                progress=replace(self._status.progress,
                                                 elapsed=time.monotonic() - self._started))
            self._claimed, self._status = False, None
            self._idle.set()
            return final

    def cancel(self, timeout: float) -> bool:
        """Make the running job (and every later claim) stop; wait up to `timeout` s for it to
        release the slot. True if no job holds it any more."""
        self._cancel.set()
        return self._idle.wait(timeout)


__all__ = ['JobCancelled', 'JobStatus', 'JobSlot']
