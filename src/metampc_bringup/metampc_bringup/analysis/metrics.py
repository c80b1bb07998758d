"""Metrics of a closed-loop run, on plain arrays (and on a :class:`RunSeries`).

Samples are keyed by (episode, step), the episode counting the resets; the MpcStatus of step k
carries the reference of the output of step k + 1, and tracking pairs the two. Tracking cost:
the stage cost of eq. (mpc) with Q = I on the tracked outputs (sum of squared errors), with
RMSE per tracked output and overall; also missed ticks, input-bound violations, solve and tick
times, foreign inputs (not the controller's, :mod:`~metampc_bringup.analysis.input_sources`;
left out of every other metric), and per-``config_version`` segments with the recorded
parameter changes when a live change happened. :func:`compute_metrics` returns a dict of plain
values. Exact definitions: docs/recording.md#metrics-metricscompute_metrics-exact-definitions.
No rclpy here.
"""
from collections import Counter
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from metampc_bringup.analysis.run_series import RunSeries

# Input bounds (u_min, u_max), one value per input each.
Bounds = Tuple[Sequence[float], Sequence[float]]


def episodes(steps: Sequence[int]) -> np.ndarray:
    """Episode index per sample: starts at 0, +1 wherever the step decreases. Shape [n]."""
    steps = np.asarray(steps, dtype=np.int64)
    if steps.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([[0], np.cumsum(np.diff(steps) < 0)]).astype(np.int64)


def keys(steps: Sequence[int]) -> List[Tuple[int, int]]:
    """(episode, step) of every sample."""
    return list(zip(episodes(steps).tolist(), np.asarray(steps, dtype=np.int64).tolist()))


def reference_pairs(output_steps: Sequence[int], status_steps: Sequence[int]
                    ) -> Tuple[np.ndarray, np.ndarray]:
    """Indices (outputs, statuses) pairing output (e, k + 1) with the status of (e, k)."""
    index = {key: i for i, key in enumerate(keys(output_steps))}
    out_idx, status_idx = [], []
    for j, (episode, step) in enumerate(keys(status_steps)):
        i = index.get((episode, step + 1))
        if i is not None:
            out_idx.append(i)
            status_idx.append(j)
    return np.array(out_idx, dtype=np.int64), np.array(status_idx, dtype=np.int64)


def tracking_metrics(y: np.ndarray, r: np.ndarray, tracked: Sequence[int]) -> Dict:
    """Tracking cost and RMSE of outputs `y` [n, n_y] against references `r` [n, n_y].

    Rows whose tracked references are not all finite are dropped. Returns the number of
    samples, the cost (sum of squared errors over tracked outputs), the overall RMSE and, per
    tracked output index (a string key), its rmse, sse and max_abs_error (None without samples).
    """
    tracked = [int(i) for i in tracked]
    y = np.asarray(y, dtype=float)
    r = np.asarray(r, dtype=float)
    if y.ndim == 1:
        y, r = y[:, None], r[:, None]
    if tracked and len(y):
        keep = np.all(np.isfinite(r[:, tracked]), axis=1)
        err = y[keep][:, tracked] - r[keep][:, tracked]
    else:
        err = np.zeros((0, len(tracked)))
    n = err.shape[0]
    per_output = {}
    for col, i in enumerate(tracked):
        e = err[:, col]
        per_output[str(i)] = {
            'rmse': float(np.sqrt(np.mean(e ** 2))) if n else None,
            'sse': float(np.sum(e ** 2)),
            'max_abs_error': float(np.max(np.abs(e))) if n else None}
    return {'tracked_outputs': tracked, 'samples': n, 'cost': float(np.sum(err ** 2)),
            'rmse': float(np.sqrt(np.mean(err ** 2))) if err.size else None,
            'per_output': per_output}


def percentile_summary(values: Sequence[float]) -> Dict:
    """count, mean, p50, p99 and max of `values` (None each when empty)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {'count': 0, 'mean': None, 'p50': None, 'p99': None, 'max': None}
    return {'count': int(v.size), 'mean': float(np.mean(v)),
            'p50': float(np.percentile(v, 50)), 'p99': float(np.percentile(v, 99)),
            'max': float(np.max(v))}


def bound_violations(u: np.ndarray, u_min: Sequence[float], u_max: Sequence[float],
                     tol: float = 1e-9) -> Dict:
    """Samples of `u` [n, n_u] with a component outside its [u_min - tol, u_max + tol]
    (bounds one per input, or one number for all).

    Returns the bounds (lists), the count of such samples and the largest excess beyond the
    bounds (0 if none).
    """
    u = np.asarray(u, dtype=float)
    u_min = np.atleast_1d(np.asarray(u_min, dtype=float)).tolist()
    u_max = np.atleast_1d(np.asarray(u_max, dtype=float)).tolist()
    if u.size == 0:
        return {'u_min': u_min, 'u_max': u_max, 'violations': 0, 'max_excess': 0.0}
    u = u.reshape(len(u), -1)
    excess = np.maximum(u - np.asarray(u_max), np.asarray(u_min) - u)
    per_sample = np.max(excess.reshape(len(u), -1), axis=1)
    return {'u_min': u_min, 'u_max': u_max, 'violations': int(np.sum(per_sample > tol)),
            'max_excess': float(max(0.0, np.max(per_sample)))}


def tick_accounting(output_steps: Sequence[int], input_steps: Sequence[int]) -> Dict:
    """Answered and missed plant steps, from the first answered step up to, not including,
    the last output (whose answer may come after the recording stopped)."""
    answered = set(keys(input_steps))
    out_keys = keys(output_steps)
    first = next((i for i, key in enumerate(out_keys) if key in answered), None)
    if first is None:
        return {'considered': 0, 'answered': 0, 'missed': 0}
    window = out_keys[first:len(out_keys) - 1]
    hits = sum(1 for key in window if key in answered)
    return {'considered': len(window), 'answered': hits, 'missed': len(window) - hits}


def version_segments(versions: Sequence[int]) -> List[Tuple[int, int]]:
    """[start, end) index ranges of the runs of equal values in `versions`, in order."""
    v = np.asarray(versions, dtype=np.int64)
    if v.size == 0:
        return []
    edges = [0, *(np.flatnonzero(np.diff(v) != 0) + 1).tolist(), v.size]
    return list(zip(edges[:-1], edges[1:]))


def step_ranges(steps: Sequence[int], episode: Sequence[int]) -> List[Dict]:
    """Per episode of a step-indexed stretch (`steps` [n] with their `episode` [n]), in order:
    its episode, first and last step; a range never spans a plant reset."""
    steps, episode = np.asarray(steps, dtype=np.int64), np.asarray(episode, dtype=np.int64)
    return [{'episode': int(episode[a]), 'first_step': int(steps[a]),
             'last_step': int(steps[b - 1])} for a, b in version_segments(episode)]


def tracking_segments(series: RunSeries, oi: np.ndarray, si: np.ndarray,
                      tracked: Sequence[int]) -> List[Dict]:
    """Tracking metrics per run of one config_version in the statuses (pairs `oi`, `si` of
    :func:`reference_pairs`); [] when the version never changes."""
    st = series.status
    segments = version_segments(st.config_version)
    if len(segments) < 2:
        return []
    episode = episodes(st.step)
    return [{'config_version': int(st.config_version[a]), 'first_step': int(st.step[a]),
             'last_step': int(st.step[b - 1]), 'statuses': b - a,
             'ranges': step_ranges(st.step[a:b], episode[a:b]),
             'tracking': tracking_metrics(series.outputs.y[oi[(si >= a) & (si < b)]],
                                          st.y_ref0[si[(si >= a) & (si < b)]], tracked)}
            for a, b in segments]


TERMINAL_PHASES = ('done', 'failed')    # TrainingProgress phases that end a job


def training_summary(series: RunSeries) -> List[Dict]:
    """Per (job, phase, method) of TrainingProgress: last iteration, total, loss, elapsed.

    The job is the phase of the training that ran ('meta_train', 'adapt', ...). A final
    'done' or 'failed' message belongs to the job whose messages precede it (the learner
    publishes iteration 0 when a job starts), so the end of a meta-training and of an
    adaptation are rows of their own.
    """
    p = series.progress
    last: Dict[Tuple[str, str, str], int] = {}
    counts: Counter = Counter()
    running: Dict[str, str] = {}    # method -> phase of its latest running job
    for i, (phase, method) in enumerate(zip(p.phase, p.method)):
        if phase not in TERMINAL_PHASES:
            running[method] = phase
        key = (running.get(method, ''), phase, method)
        last[key] = i
        counts[key] += 1
    return [{'job': job, 'phase': phase, 'method': method, 'iteration': int(p.iteration[i]),
             'total': int(p.total[i]), 'final_loss': float(p.loss[i]),
             'elapsed': float(p.elapsed[i]), 'skipped_tasks': int(p.skipped_tasks[i]),
             'messages': counts[(job, phase, method)]}
            for (job, phase, method), i in last.items()]


FOREIGN_STEPS_LISTED = 20   # steps of foreign inputs named in the report, at most


def foreign_inputs(series: RunSeries) -> Dict:
    """ControlInputs that are not the controller's answers (input_sources): how many, the
    steps of the first FOREIGN_STEPS_LISTED and their log times, ns."""
    f = series.foreign_inputs
    return {'count': int(f.step.size), 'steps': f.step[:FOREIGN_STEPS_LISTED].tolist(),
            'log_times': f.log_time[:FOREIGN_STEPS_LISTED].tolist()}


def compute_metrics(series: RunSeries, tracked: Optional[Sequence[int]] = None,
                    u_bounds: Optional[Bounds] = None) -> Dict:
    """All metrics of a run, JSON-ready.

    Args:
        series: the run's series.
        tracked: output indices that follow a reference (default: all outputs).
        u_bounds: (u_min, u_max), one per input; default from PlantInfo, else bound checks
            are skipped.
    """
    out, inp, st = series.outputs, series.inputs, series.status
    if tracked is None:
        tracked = list(range(series.n_y))
    oi, si = reference_pairs(out.step, st.step)
    if u_bounds is None and series.plant_info is not None:
        # Older recordings hold one number per bound, newer ones a list per input.
        u_bounds = tuple(np.atleast_1d(np.asarray(series.plant_info[key], dtype=float))
                         for key in ('u_min', 'u_max'))
    diverged = np.flatnonzero(out.diverged)
    solved = st.iterations >= 0
    metrics = {
        'samples': {'outputs': int(out.step.size), 'inputs': int(inp.step.size),
                    'mpc_status': int(st.step.size), 'weights': len(series.weights),
                    'progress': int(series.progress.loss.size)},
        'tracking': tracking_metrics(out.y[oi], st.y_ref0[si], tracked),
        'input_bounds': (bound_violations(inp.u, *u_bounds) if u_bounds is not None
                         else None),
        'saturated_samples': int(np.sum(out.saturated)),
        'diverged_samples': int(diverged.size),
        'first_diverged_step': int(out.step[diverged[0]]) if diverged.size else None,
        'ticks': tick_accounting(out.step, inp.step),
        'foreign_inputs': foreign_inputs(series),
        'solve_time': percentile_summary(st.solve_time[solved]),
        'tick_time': percentile_summary(st.tick_time),
        'fallbacks': int(np.sum(st.fallback)),
        'terminal_fallbacks': int(np.sum(st.terminal_fallback)),
        'solver_status': dict(Counter(st.solver_status)),
        'planner': dict(Counter(st.planner)),
        'model_versions': {'published': [w['version'] for w in series.weights],
                           'used_by_inputs': sorted(set(inp.model_version.tolist()))},
        'training': training_summary(series),
    }
    segments = tracking_segments(series, oi, si, tracked)
    if segments:
        metrics['tracking_segments'] = segments
    if series.parameter_changes:
        metrics['parameter_changes'] = [
            {k: change[k] for k in ('stamp', 'node', 'parameters')}
            for change in series.parameter_changes]
    return metrics
