"""Adaptation in the loop, the learner's side: the latest target samples, and what one
request of the controller adapts on.

Pure Python (no rclpy). :class:`RecentSamples` keeps the latest samples of the running
episode; a request (``MpcStatus.adapt_request``, step r) is answered with eq. (infer) on the
``loop_window`` latest samples up to r, from the model in use, anchored to its method's
meta-model by ``loop_gamma/2 ||psi - omega_inf||^2`` (a model without one, to itself), run by
:meth:`LearnerSession.loop_adapt`. Refuses (:meth:`RecentSamples.refusal`, the reason in the
log) a window with diverged or non-finite samples or outputs that never changed: nothing left
to learn from. Why: docs/adaptation.md.
"""
from collections import deque
from dataclasses import dataclass
import threading
from typing import Deque, Tuple

import numpy as np

from metampc_common.params import check_fields, param
from metampc_learner.target_buffer import TargetSamples, usable


@dataclass
class LoopConfig:
    """The loop_* parameters of the learner (see the module docstring)."""

    adaptation: bool = param(False, "answer the controller's adaptation requests (its "
                                    'adaptation parameter): keep the latest samples, adapt')
    window: int = param(0, 'latest samples up to the request step adapted on (0: '
                           'target_buffer_size; at most that)', ge=0)
    steps: int = param(10, 'adaptation steps per request', ge=1)
    lr: float = param(0.0, 'step size (0: adapt_lr)', ge=0)
    gamma: float = param(1.0, 'proximal strength towards the meta-model of eq. infer', ge=0)

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)


# Samples kept beyond the window: the plant runs on while a request waits for its job (up to
# the swap step under lockstep; in real time for as long as the learner is late), and the
# window up to the request step must be whole whatever arrived since (a lockstep run is then
# the same on any machine).
BEYOND_WINDOW = 1000


class RecentSamples:
    """The latest `capacity` valid samples (step k, u_k, y_k) of the running episode.

    A step that does not follow the previous one by more than zero (a reset: the step
    restarts) starts a new episode and empties it; y_0 of an episode, diverged and non-finite
    samples are not kept (as in D_target), their steps are (the latest `capacity`, for
    :meth:`refusal`). Thread-safe: the node adds from its subscription, a job reads
    :meth:`until`.
    """

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f'capacity must be >= 1, got {capacity}')
        self.capacity = capacity
        self._samples: Deque[Tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=capacity)
        self._unusable: Deque[int] = deque(maxlen=capacity)    # steps > 0 not kept
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self.last_step = -1     # the newest step offered in this episode (-1: none)

    def add(self, step: int, u, y, diverged: bool = False) -> None:
        """Offer sample k of the plant's y topic."""
        with self._cond:
            if step <= self.last_step:
                self._samples.clear()
                self._unusable.clear()
            self.last_step = int(step)
            u = np.array(u, dtype=np.float64).reshape(-1)
            y = np.array(y, dtype=np.float64).reshape(-1)
            if usable(step, u, y, diverged):
                self._samples.append((int(step), u, y))
            elif step > 0:
                self._unusable.append(int(step))
            self._cond.notify_all()

    def wait_for(self, step: int, timeout: float) -> bool:
        """Wait until sample `step` (or a later one) has been offered; False after
        `timeout` s (the request's status can overtake its y: two publishers)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.last_step >= step, timeout)

    def refusal(self, step: int, n: int) -> str:
        """Why the window of :meth:`until` (`step`, `n`) is no data to adapt on, or ''.

        Refused: a diverged or non-finite sample offered between the window's first kept
        sample and `step` (the plant escaped, or its data has holes the window would skip),
        or outputs all equal over the window (the plant stopped changing)."""
        with self._lock:
            kept = [s for s in self._samples if s[0] <= step][-n:]
            first = kept[0][0] if kept else 0
            bad = [k for k in self._unusable if first <= k <= step]
        if bad:
            return (f'{len(bad)} of the samples from step {first} to {step} (the first at '
                    f'step {bad[0]}, the last at {bad[-1]}) are diverged or non-finite: the '
                    f'plant escaped or its data broke; the window would refit the samples '
                    f'before them')
        if len(kept) > 1 and all(np.array_equal(y, kept[-1][2]) for _, _, y in kept):
            return (f'the outputs did not change from step {first} to {kept[-1][0]}: the '
                    f'plant stopped changing, nothing to adapt on')
        return ''

    def until(self, step: int, n: int) -> TargetSamples:
        """The latest n kept samples with step <= `step`, oldest first."""
        with self._lock:
            kept = [s for s in self._samples if s[0] <= step][-n:]
        if not kept:
            return TargetSamples(np.zeros(0, np.int64), np.zeros((0, 1)), np.zeros((0, 1)))
        return TargetSamples(np.array([s[0] for s in kept], dtype=np.int64),
                             np.stack([s[1] for s in kept]), np.stack([s[2] for s in kept]))


__all__ = ['BEYOND_WINDOW', 'LoopConfig', 'RecentSamples']
