"""The bridge's sampling rule on a recording: samples (u_k, y_k) on the controller's grid, and
why a sample cannot be trained on.

The grid t_k = t_0 + k dt runs from the first time every output stream has a sample to the
last time every one has. y_k: each stream's newest sample stamped at or before t_k
(``sampling.hold``, the mapping's stale_timeout); u_k: the newest input stamped before t_k (the
one held over (k-1, k]; an input stamped t_k answers y_k). A sample is skipped for the first of
:data:`REASONS` that holds. docs/offline_adaptation.md.
"""
from dataclasses import dataclass
import math
from typing import Dict, List, Tuple

import numpy as np

from metampc_plant.machine_mapping import MachineMapping
from metampc_plant.sampling import held_indices, hold
from metampc_learner.recorded_streams import Recorded, RecordingError

STALE = 'stale'                     # an output stream's newest sample is older than stale_timeout
NO_INPUT = 'no_input'               # no input stamped before t_k
NOT_FINITE = 'nan'                  # a y_i or u_j is NaN or infinite (or could not be read)
REPEAT = 'repeat'                   # an output stream has no new sample since t_(k-1)
INPUT_SATURATED = 'input_saturated'     # a u_j at or beyond its [min, max]
OUTPUT_SATURATED = 'output_saturated'   # a y_i at or beyond its stated [min, max]
REASONS = (STALE, NO_INPUT, NOT_FINITE, REPEAT, INPUT_SATURATED, OUTPUT_SATURATED)
BOUND_TOLERANCE = 1e-9      # "at a bound": within this share of the range [min, max]


@dataclass
class GridSamples:
    """Samples on the grid: times (K,) s, y (K, n_y), u (K, n_u) physical (NaN where there is
    none), reasons (K,): '' for a usable sample, else the first of REASONS that holds."""

    times: np.ndarray
    y: np.ndarray
    u: np.ndarray
    reasons: np.ndarray

    @property
    def usable(self) -> np.ndarray:
        return self.reasons == ''

    def counts(self) -> Dict[str, int]:
        """Skipped samples per reason (every reason, 0 included)."""
        return {r: int(np.sum(self.reasons == r)) for r in REASONS}

    def skipped_runs(self) -> List[Tuple[int, int, str]]:
        """(first k, last k, reason) of each run of skipped samples with one reason."""
        runs: List[Tuple[int, int, str]] = []
        for k, reason in enumerate(self.reasons):
            if not reason:
                continue
            if runs and runs[-1][1] == k - 1 and runs[-1][2] == reason:
                runs[-1] = (runs[-1][0], k, reason)
            else:
                runs.append((k, k, reason))
        return runs


def _at_bound(values: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(K,) whether any value (K, m) is at or beyond [low, high] (m,)."""
    span = np.where(np.isfinite(high - low), high - low, 0.0)
    margin = BOUND_TOLERANCE * span
    with np.errstate(invalid='ignore'):
        return np.any((values <= low + margin) | (values >= high - margin), axis=1)


def grid_samples(recorded: Recorded, mapping: MachineMapping, keep_saturated: bool = False
                 ) -> GridSamples:
    """The samples of the module docstring; `keep_saturated`: inputs at or beyond their bounds
    are kept, clipped to [min, max] (the bridge clips what it writes there).

    Raises:
        RecordingError: no time at which every output stream has a sample.
    """
    streams = recorded.outputs
    if any(len(s.stamps) == 0 for s in streams):
        raise RecordingError('an output stream of the recording has no samples')
    t0 = max(s.stamps[0] for s in streams)
    t_end = min(s.stamps[-1] for s in streams)
    if t_end < t0:
        raise RecordingError(f'the output streams do not overlap in time ({t0:.3f} s is after '
                             f'{t_end:.3f} s)')
    times = t0 + mapping.dt * np.arange(math.floor((t_end - t0) / mapping.dt + 1e-9) + 1)
    n_y = len(mapping.outputs)
    y = np.full((len(times), n_y), np.nan)
    stale = np.zeros(len(times), dtype=bool)
    repeat = np.zeros(len(times), dtype=bool)
    for stream in streams:
        held, fresh = hold(stream.stamps, stream.values, times, mapping.stale_timeout)
        y[:, list(stream.columns)] = held
        stale |= ~fresh
        index = held_indices(stream.stamps, times)
        repeat[1:] |= index[1:] == index[:-1]
    command = recorded.command
    u, has_input = hold(command.stamps, command.values, np.nextafter(times, -np.inf), math.inf)
    finite = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(u), axis=1)
    saturated = _at_bound(u, mapping.u_min, mapping.u_max)
    if keep_saturated:
        u = np.clip(u, mapping.u_min, mapping.u_max)
        saturated[:] = False
    checks = ((STALE, stale), (NO_INPUT, ~has_input), (NOT_FINITE, ~finite), (REPEAT, repeat),
              (INPUT_SATURATED, saturated),
              (OUTPUT_SATURATED, _at_bound(y, mapping.y_min, mapping.y_max)))
    reasons = np.full(len(times), '', dtype=object)
    for reason, hit in reversed(checks):
        reasons[hit] = reason
    return GridSamples(times, y, u, reasons)


__all__ = ['GridSamples', 'grid_samples', 'REASONS', 'STALE', 'NO_INPUT', 'NOT_FINITE',
           'REPEAT', 'INPUT_SATURATED', 'OUTPUT_SATURATED']
