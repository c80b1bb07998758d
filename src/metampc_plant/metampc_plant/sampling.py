"""The machine bridge's sampling rule: stamped samples held onto the controller's grid.

Sample k of the controller is taken at t_k = t_0 + k dt. Each stream gives its newest sample
with stamp <= t_k (a zero-order hold: no interpolation, nothing from after t_k); the stream is
stale at t_k when it has no such sample or the newest is older than the stale timeout
(t_k - stamp > stale_timeout). The same function serves a live bridge (one tick at a time,
:class:`SampleStream`) and an offline reader of a recording (a whole grid, :func:`hold`).
Times in s, on one clock. docs/bridge.md.
"""
import bisect
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np


def held_indices(stamps: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Index of the newest sample with stamp <= each time (-1: none), for non-decreasing
    stamps (n,) and any times (K,); ties go to the last sample of that stamp."""
    return np.searchsorted(stamps, times, side='right') - 1


def hold(stamps: Sequence[float], values: np.ndarray, times: Sequence[float],
         stale_timeout: float) -> Tuple[np.ndarray, np.ndarray]:
    """The rule on a grid: (held values (K, m), NaN where stale; fresh (K,) bool).

    Args:
        stamps: sample times (n,), non-decreasing, s.
        values: samples (n, m).
        times: grid times t_k (K,), s.
        stale_timeout: s; a sample older than this at t_k is stale there.
    """
    stamps, times = np.asarray(stamps, dtype=float), np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    out = np.full((len(times), values.shape[1]), np.nan)
    if not len(stamps):
        return out, np.zeros(len(times), dtype=bool)
    index = held_indices(stamps, times)
    fresh = (index >= 0) & (times - stamps[np.maximum(index, 0)] <= stale_timeout)
    out[fresh] = values[index[fresh]]
    return out, fresh


def grid_step(previous: Optional[int], elapsed: float, dt: float) -> int:
    """The step k of a tick `elapsed` s after the tick of step 0: the whole periods elapsed,
    at least previous + 1 (a timer that fires a little early still makes the next step; one
    that missed periods skips their steps)."""
    k = math.floor(elapsed / dt + 1e-9)
    return k if previous is None else max(previous + 1, k)


class SampleStream:
    """The samples of one stream, kept sorted by stamp, held by the rule one tick at a time.

    Samples that can no longer be held (older than the one held at the latest tick) are
    dropped, so the stream stays short.
    """

    def __init__(self):
        self._stamps: List[float] = []
        self._values: List[np.ndarray] = []

    def add(self, stamp: float, values: Sequence[float]) -> None:
        """A sample (in any order of stamps)."""
        i = bisect.bisect_right(self._stamps, stamp)
        self._stamps.insert(i, stamp)
        self._values.insert(i, np.asarray(values, dtype=float))

    def at(self, t: float) -> Tuple[Optional[np.ndarray], float]:
        """(values of the newest sample with stamp <= t, its age t - stamp in s), or (None,
        inf) if there is none; samples older than it are dropped (ticks only go forward)."""
        index = int(held_indices(np.asarray(self._stamps), np.asarray([t]))[0])
        if index < 0:
            return None, math.inf
        del self._stamps[:index], self._values[:index]
        return self._values[0], t - self._stamps[0]
