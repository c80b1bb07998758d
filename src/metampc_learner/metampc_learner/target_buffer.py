"""D_target: a bounded buffer of target samples (step k, u_k, y_k), and its train/held-out split.

u_k (``u_applied``) was held over (k-1, k] and produced y_k. The buffer keeps the first
``capacity`` valid samples after :meth:`start` and ignores the rest (:meth:`freeze` stops it
early); it skips and counts samples flagged diverged, non-finite, of the wrong size or of step
0, and counts those that never arrived (a step index that jumps ahead). Thread-safe: the node
adds from its subscription while training reads a snapshot. :func:`split_target` turns a
snapshot into trajectories: the first ``n_samples`` in arrival order, cut into a training part
and the held-out last ``heldout_fraction``, each cut again wherever the step does not advance by
one, so no window spans a gap. See docs/learner.md.
"""
import threading
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np

from metampc_learner.data import trajectories_from_samples, Trajectory


@dataclass
class TargetSamples:
    """A snapshot, in arrival order: steps (K,) int64, u (K, n_u), y (K, n_y), physical."""

    steps: np.ndarray
    u: np.ndarray
    y: np.ndarray

    def __len__(self) -> int:
        return self.steps.shape[0]


def usable(step: int, u: np.ndarray, y: np.ndarray, diverged: bool) -> bool:
    """Whether a sample can be trained on: not y_0 of an episode (no input produced it), not
    diverged, u and y non-empty and finite."""
    return (step > 0 and not diverged and u.size > 0 and y.size > 0
            and bool(np.all(np.isfinite(u))) and bool(np.all(np.isfinite(y))))


class TargetBuffer:
    """The first `capacity` valid target samples since the last :meth:`start` (see module)."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f'capacity must be >= 1, got {capacity}')
        self.capacity = capacity
        self._lock = threading.Lock()
        self._steps: List[int] = []
        self._u: List[np.ndarray] = []
        self._y: List[np.ndarray] = []
        self._enabled = True
        self.skipped = 0
        self.lost = 0
        self._last_step = None      # step of the last sample offered while buffering

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def full(self) -> bool:
        return len(self._steps) >= self.capacity

    def __len__(self) -> int:
        return len(self._steps)

    def start(self) -> int:
        """Clear the buffer and (re)start buffering; returns the number of samples cleared."""
        with self._lock:
            cleared = len(self._steps)
            self._steps, self._u, self._y = [], [], []
            self.skipped = self.lost = 0
            self._last_step = None
            self._enabled = True
            return cleared

    def freeze(self) -> None:
        """Stop buffering; the samples so far are kept."""
        self._enabled = False

    def add(self, step: int, u: Sequence[float], y: Sequence[float],
            diverged: bool = False) -> bool:
        """Offer one sample; True if it was stored.

        Not stored: buffering off or full (not counted), or skipped and counted in `skipped`:
        diverged, step 0, non-finite, or sizes differing from the first stored sample. Samples
        missing before this one (its step more than one past the last offered one, or past 1
        in a new episode) are counted in `lost`.
        """
        with self._lock:
            if not self._enabled or self.full:
                return False
            last, self._last_step = self._last_step, int(step)
            if last is not None:
                self.lost += max(step - last - 1, 0) if step > last else max(step - 1, 0)
            u = np.array(u, dtype=np.float64).reshape(-1)
            y = np.array(y, dtype=np.float64).reshape(-1)
            shape_ok = not self._steps or (u.shape == self._u[0].shape
                                           and y.shape == self._y[0].shape)
            if not (shape_ok and usable(step, u, y, diverged)):
                self.skipped += 1
                return False
            self._steps.append(int(step))
            self._u.append(u)
            self._y.append(y)
            return True

    def snapshot(self) -> TargetSamples:
        """Copies of the stored samples, in arrival order."""
        with self._lock:
            if not self._steps:
                return TargetSamples(np.zeros(0, np.int64), np.zeros((0, 1)), np.zeros((0, 1)))
            return TargetSamples(np.array(self._steps, dtype=np.int64), np.stack(self._u),
                                 np.stack(self._y))


def _runs(samples: TargetSamples, state_bound: float) -> List[Trajectory]:
    """Trajectories of consecutive steps, in arrival order (split where step != previous + 1)."""
    if len(samples) == 0:
        return []
    cuts = np.flatnonzero(np.diff(samples.steps) != 1) + 1
    out: List[Trajectory] = []
    for part in np.split(np.arange(len(samples)), cuts):
        out.extend(trajectories_from_samples(samples.steps[part], samples.u[part],
                                             samples.y[part], state_bound))
    return out


def split_target(samples: TargetSamples, n_samples: int, heldout_fraction: float,
                 state_bound: float) -> Tuple[List[Trajectory], List[Trajectory], int]:
    """(training trajectories, held-out trajectories, samples used) of D_target.

    Args:
        samples: a buffer snapshot.
        n_samples: use the first n_samples (0 or more than buffered: all).
        heldout_fraction: the last round(fraction * n) samples in arrival order are held out.
        state_bound: samples with |y|_inf beyond it are dropped (the data core's rule).
    """
    n = len(samples) if n_samples <= 0 else min(n_samples, len(samples))
    cut = n - int(round(heldout_fraction * n))
    parts = [TargetSamples(samples.steps[a:b], samples.u[a:b], samples.y[a:b])
             for a, b in ((0, cut), (cut, n))]
    return _runs(parts[0], state_bound), _runs(parts[1], state_bound), n


__all__ = ['TargetSamples', 'TargetBuffer', 'split_target', 'usable']
