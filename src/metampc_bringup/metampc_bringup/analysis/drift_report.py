"""Scenario drift's results from its recordings alone (docs/adaptation.md).

Per tracking run of a drift seed (``<method>/<mode>``, modes 'none', 'periodic', 'triggered'
and 'constant'; the NMPC's ``nmpc``), from the outputs and statuses stamped within its span:
the tracking cost before and after the first theta change, as a ratio to the NMPC's on the
same samples; the time to recover (the 5-s moving cost over the NMPC's back within
:data:`RECOVERY_FACTOR` after the change); the adaptation requests, swaps and their compute
times, and the models the controller refused or reverted (its model events, with the reason);
the detector's error over time (plotted). :func:`drift_experiment_report` gathers the seeds
into report.json and report.md (median and worst seed per method and mode; each adapting mode
against 'none' of the same method, paired by seed; the spurious adaptations of the constant
runs). No rclpy here.
"""
import json
import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import matplotlib
import numpy as np

from metampc_bringup.analysis.experiment_report import STAMP_TOL
from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.experiment_config import DriftConfig
from metampc_bringup.experiment_events import (Done, ExperimentEvent, read_events, Start, TrackEnd,
                                               TrackStart)
from metampc_controller.adaptation_trigger import TriggerConfig
from metampc_recording.recording_reader import read_recording

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

MOVING_WINDOW_S = 5.0
RECOVERY_FACTOR = 1.2
PLANT_OUTPUT = 'metampc_msgs/msg/PlantOutput'
MPC_STATUS = 'metampc_msgs/msg/MpcStatus'
NSSM_WEIGHTS = 'metampc_msgs/msg/NssmWeights'


@dataclass
class RunSignals:
    """One run's signals. Outputs (n = steps + 1): t [n] s since the run's start, y [n, n_y],
    theta [n, n_theta]; statuses (one per answered step k): step [m], model_version [m],
    error_t [m] (T-step prediction error), change_t [m] (the outputs' T-step change),
    request [m] (bool), trigger [m], ref [m, n_y]
    (reference of the output of step k + 1); compute [a] s: the training time of each online
    model the run used; events [m]: each status's model events (metampc_msgs/ModelEvent:
    outcome, cause, reason; none in recordings from before them)."""

    t: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    step: np.ndarray
    model_version: np.ndarray
    error_t: np.ndarray
    change_t: np.ndarray
    request: np.ndarray
    trigger: List[str]
    ref: np.ndarray
    compute: List[float]
    events: List[Sequence[Any]] = field(default_factory=list)


def drift_runs(events: List[ExperimentEvent]) -> Dict[str, Dict[str, Any]]:
    """Per run name: its start and end stamps (s), steps, method, escape and schedule."""
    starts = {e.run_name: e for e in events if isinstance(e, TrackStart)}
    runs = {}
    for e in events:
        if isinstance(e, TrackEnd) and e.run_name in starts:
            start = starts[e.run_name]
            runs[e.run_name] = {'method': e.method, 'start': start.stamp, 'end': e.stamp,
                                'steps': int(e.steps), 'diverged': bool(e.diverged),
                                'schedule': list(start.theta_schedule or [])}
    return runs


def run_signals(recording, runs: Dict[str, Dict[str, Any]]) -> Dict[str, RunSignals]:
    """The signals of every run, cut out of the recording by their stamps."""
    rows = {name: {'out': [], 'status': []} for name in runs}
    topics = [t.name for t in recording.topics.values()
              if t.type_name in (PLANT_OUTPUT, MPC_STATUS)]
    for topic, raw, msg in recording.decoded(topics):
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        answer = topic.type_name == MPC_STATUS
        for name, run in runs.items():
            last = run['end'] - STAMP_TOL if answer else run['end'] + STAMP_TOL
            if run['start'] - STAMP_TOL <= stamp <= last:
                rows[name]['status' if answer else 'out'].append((stamp - run['start'], msg))
    # The learner's training time of every online model, by version (NssmWeights.train_time;
    # none in recordings made before the field).
    trained = {int(msg.version): float(msg.train_time) for _, _, msg in recording.decoded(
        [t.name for t in recording.topics.values() if t.type_name == NSSM_WEIGHTS])
        if msg.stage == 'online' and hasattr(msg, 'train_time')}
    out = {}
    for name, r in rows.items():
        outs = sorted(r['out'], key=lambda p: p[1].step)
        stats = sorted(r['status'], key=lambda p: p[1].step)
        n_y = len(outs[0][1].y) if outs else 1
        versions = sorted({int(m.model_version) for _, m in stats})
        out[name] = RunSignals(
            t=np.array([t for t, _ in outs]), y=np.array([list(m.y) for _, m in outs]),
            theta=np.array([list(m.theta) for _, m in outs]),
            step=np.array([m.step for _, m in stats], dtype=np.int64),
            model_version=np.array([m.model_version for _, m in stats], dtype=np.int64),
            error_t=np.array([m.prediction_error_t for _, m in stats], dtype=float),
            change_t=np.array([m.output_change_t for _, m in stats], dtype=float),
            request=np.array([bool(m.adapt_request) for _, m in stats], dtype=bool),
            trigger=[m.adapt_trigger for _, m in stats],
            ref=np.array([list(m.y_ref[:n_y]) for _, m in stats], dtype=float
                         ).reshape(len(stats), n_y),
            compute=[trained[v] for v in versions if v in trained],
            events=[getattr(m, 'model_events', ()) for _, m in stats])
    return out


def squared_errors(sig: RunSignals, tracked: Sequence[int]) -> np.ndarray:
    """(m,) squared tracking error of the output of step k + 1 against the reference of the
    status of step k, summed over the tracked outputs (NaN where there is none)."""
    index = {int(k): i for i, k in enumerate(np.round(sig.t / _dt(sig)).astype(int))}
    e2 = np.full(len(sig.step), np.nan)
    for j, k in enumerate(sig.step):
        i = index.get(int(k) + 1)
        if i is not None:
            e2[j] = float(np.sum((sig.y[i, tracked] - sig.ref[j, tracked]) ** 2))
    return e2


def _dt(sig: RunSignals) -> float:
    return float(sig.t[1] - sig.t[0]) if len(sig.t) > 1 else 1.0


def moving_cost(e2: np.ndarray, samples: int) -> np.ndarray:
    """Trailing mean of e2 over `samples` samples (fewer at the start; NaN ignored)."""
    good = np.where(np.isfinite(e2), e2, 0.0)
    count = np.isfinite(e2).astype(float)
    sums = np.convolve(good, np.ones(samples))[:len(e2)]
    counts = np.convolve(count, np.ones(samples))[:len(e2)]
    with np.errstate(invalid='ignore', divide='ignore'):
        return sums / counts


def _after(t: np.ndarray, t_change: float) -> np.ndarray:
    """Which output times lie after t_change; one at t_change, to within float error, is
    before (as n dt against a schedule's time)."""
    return t > t_change + 1e-9 * max(1.0, abs(t_change))


def recovery_time(ratio: np.ndarray, t: np.ndarray, t_change: float,
                  factor: float = RECOVERY_FACTOR) -> Optional[float]:
    """After t_change: 0 if `ratio` never exceeds `factor`; else the first time it is back
    within after it first exceeded, minus t_change; None if it never is."""
    after = np.flatnonzero(_after(t, t_change))
    over = [i for i in after if ratio[i] > factor]
    if not over:
        return 0.0
    back = [i for i in after if i > over[0] and ratio[i] <= factor]
    return float(t[back[0]] - t_change) if back else None


def _mean(values: np.ndarray) -> Optional[float]:
    """The mean of the finite values; None when there is none (a run that escaped early)."""
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


def refusals(sig: RunSignals) -> List[List[Any]]:
    """[step, reason, kind] of each model the controller refused (kind 'check': by the check,
    'weights': weights it could not build) or reverted after its probation ('revert'; the
    reason begins 'reverted: '), from the model events of its statuses."""
    out = []
    for step, events in zip(sig.step, sig.events):
        for event in events:
            if event.outcome == 'reverted':
                out.append([int(step), f'reverted: {event.reason}', 'revert'])
            elif event.outcome == 'refused':
                out.append([int(step), event.reason, event.cause])
    return out


def run_metrics(sig: RunSignals, nmpc: Optional[RunSignals], t_change: Optional[float],
                tracked: Sequence[int], dt: float) -> Dict[str, Any]:
    """The metrics of one run (module docstring); `t_change` None: a constant run; `dt` the
    sample time, s (the run's, not one taken from its stamps: their differences carry the
    float error of the run's start, which moved an output at t_change from one side to the
    other between identical runs)."""
    e2 = squared_errors(sig, tracked)
    t = (sig.step + 1) * dt     # the time of the output each error is of
    swaps = [int(sig.step[i]) for i in range(1, len(sig.step))     # reverts are no swap
             if sig.model_version[i] != sig.model_version[i - 1]
             and not any(e.outcome == 'reverted' for e in sig.events[i])]
    refused = refusals(sig)
    kinds: Dict[str, int] = {}
    for _, _, kind in refused:
        kinds[kind] = kinds.get(kind, 0) + 1
    out: Dict[str, Any] = {
        'steps': int(len(sig.step)), 'cost': _mean(e2),
        'requests': [[int(k), tr] for k, r, tr in zip(sig.step, sig.request, sig.trigger) if r],
        'swaps': swaps, 'compute_s': sig.compute,
        'adaptations': len(swaps), 'refusals': [r[:2] for r in refused],
        'refusal_kinds': kinds}
    if t_change is None:
        return out
    after = _after(t, t_change)
    before = ~after
    out['cost_before'], out['cost_after'] = _mean(e2[before]), _mean(e2[after])
    if nmpc is not None:
        ref = squared_errors(nmpc, tracked)
        n = min(len(ref), len(e2))
        for key, part in (('ratio_before', before[:n]), ('ratio_after', after[:n])):
            mine, yardstick = _mean(e2[:n][part]), _mean(ref[:n][part])
            out[key] = None if mine is None or not yardstick else mine / yardstick
        window = max(1, int(round(MOVING_WINDOW_S / dt)))
        with np.errstate(invalid='ignore', divide='ignore'):
            ratio = moving_cost(e2[:n], window) / moving_cost(ref[:n], window)
        out['recovery_s'] = recovery_time(ratio, t[:n], t_change)
    return out


def plot_run(signals: Dict[str, RunSignals], method: str, dt: float, floor: float,
             path: str) -> str:
    """The change detector's relative T-step prediction error E / (D + floor) of a method's
    runs over time, requests (x) and swaps (vertical lines) marked, and the plant's theta
    below."""
    runs = [name for name in signals if name.split('/')[0] == method]
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 6), sharex=True,
                                 gridspec_kw={'height_ratios': [3, 1]})
    for name in runs:
        sig = signals[name]
        t = sig.step * dt
        rel = sig.error_t / (sig.change_t + floor)
        line, = ax.semilogy(t, rel, lw=0.9, label=name.split('/', 1)[1])
        req = sig.request
        ax.plot(t[req], rel[req], 'x', color=line.get_color(), ms=7)
        for i in range(1, len(sig.step)):
            if sig.model_version[i] != sig.model_version[i - 1]:
                ax.axvline(t[i], color=line.get_color(), lw=0.6, ls=':')
        if len(sig.theta) and sig.theta.shape[1]:
            bx.plot(sig.t, sig.theta[:, 0], color=line.get_color(), lw=0.9)
    ax.set_ylabel('relative T-step error E / (D + floor)')
    ax.set_title(f'{method}: relative T-step prediction error (x: requests, dotted: swaps)')
    ax.legend(fontsize=8)
    bx.set_ylabel('theta[0]')
    bx.set_xlabel('t [s]')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def seed_drift_report(path: str, out_dir: Optional[str] = None, plots: bool = True
                      ) -> Dict[str, Any]:
    """Report of one drift seed's recording; writes report.json (and the figures)."""
    recording = read_recording(path)
    out_dir = out_dir or os.path.dirname(os.path.abspath(recording.path))
    events = read_events(recording)
    start = next((e for e in events if isinstance(e, Start)), None)
    if start is None:
        raise ValueError(f'{recording.path} holds no experiment events')
    config = recording.run_config()
    experiment = config.get('experiment', {})
    drift = DriftConfig(**experiment.get('drift', {}))
    tracked = [int(i) for i in config.get('tracked_outputs', [0])]
    runs = drift_runs(events)
    signals = run_signals(recording, runs)
    n_theta = len(start.theta)
    t_change = min(drift.change_times(n_theta)) if drift.schedule else None
    nmpc = signals.get('nmpc')
    dt = float(experiment.get('dt') or _dt(next(iter(signals.values()))))
    metrics = {}
    for name, sig in signals.items():
        constant = not runs[name]['schedule']
        metrics[name] = run_metrics(sig, None if name == 'nmpc' else nmpc,
                                    None if constant else t_change, tracked, dt)
        metrics[name]['escaped'] = runs[name]['diverged']
    figures = []
    if plots:
        floor = float((experiment.get('controller') or {}).get(
            'error_floor', TriggerConfig().error_floor))
        for method in drift.methods:
            figures.append(os.path.basename(plot_run(
                signals, method, dt, floor, os.path.join(out_dir, f'drift_{method}.png'))))
    done = next((e for e in events if isinstance(e, Done)), None)
    report = json_safe({
        'recording': os.path.abspath(recording.path), 'seed': start.seed,
        'theta': start.theta, 'complete': recording.complete and done is not None,
        't_change': t_change, 'runs': metrics, 'figures': figures,
        'timings': done.timings if done else None})
    with open(os.path.join(out_dir, 'report.json'), 'w') as f:
        json.dump(report, f, indent=2, sort_keys=True)
    return report


def _stats(values: List[Optional[float]]) -> Dict[str, Any]:
    """Median and worst (largest; a None, 'never', is worst) over seeds."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    never = sum(v is None for v in values)
    return {'median': float(np.median(finite)) if finite and never <= len(values) // 2
            else None,
            'worst': None if never else (max(finite) if finite else None),
            'never': never, 'values': values}


def drift_experiment_report(seed_reports: List[Dict], out_dir: str, config: Dict[str, Any],
                            wall_time_s: float) -> Dict[str, Any]:
    """Gather the drift seeds into report.json and report.md (module docstring)."""
    drift = DriftConfig(**config.get('drift', {}))
    table = {}
    for method in drift.methods:
        for mode in [*drift.modes, *(['constant'] if drift.constant_check else [])]:
            name = f'{method}/{mode}'
            per = [r['runs'].get(name, {}) for r in seed_reports]
            kinds: Dict[str, int] = {}
            for p in per:
                for kind, n in p.get('refusal_kinds', {}).items():
                    kinds[kind] = kinds.get(kind, 0) + n
            table[name] = {
                'refusals': [len(p.get('refusals', [])) for p in per], 'refusal_kinds': kinds,
                'vs_none': _paired(per, [r['runs'].get(f'{method}/none', {})
                                         for r in seed_reports])
                if mode not in ('none', 'constant') and 'none' in drift.modes else None,
                'recovery_s': _stats([p.get('recovery_s') for p in per]),
                'ratio_after': _stats([p.get('ratio_after') for p in per]),
                'ratio_before': _stats([p.get('ratio_before') for p in per]),
                'adaptations': [p.get('adaptations') for p in per],
                'compute_s': [c for p in per for c in p.get('compute_s', [])],
                'escapes': sum(bool(p.get('escaped')) for p in per)}
    report = json_safe({'scenario': 'drift', 'seeds': [r['seed'] for r in seed_reports],
                        'thetas': [r['theta'] for r in seed_reports], 'table': table,
                        'wall_time_s': wall_time_s, 'config': config,
                        'per_seed': seed_reports})
    with open(os.path.join(out_dir, 'report.json'), 'w') as f:
        json.dump(report, f, indent=2, sort_keys=True)
    with open(os.path.join(out_dir, 'report.md'), 'w') as f:
        f.write(drift_markdown(report, drift))
    return report


def _paired(runs: List[Dict], none: List[Dict]) -> Dict[str, Any]:
    """Per seed, the cost after the change of an adapting run over that of the same method's
    'none' run (the same seed, plant and reference): values, how many are above 1 (worse),
    the worst, and their geometric mean."""
    values = [a['cost_after'] / b['cost_after']
              if a.get('cost_after') is not None and b.get('cost_after') else None
              for a, b in zip(runs, none)]
    finite = [v for v in values if v is not None and math.isfinite(v) and v > 0]
    return {'values': values, 'worse': sum(v > 1.0 for v in finite),
            'worst': max(finite) if finite else None,
            'geomean': float(np.exp(np.mean(np.log(finite)))) if finite else None}


def _fmt(v: Optional[float], unit: str = '', none: str = 'never') -> str:
    return none if v is None else f'{v:.3g}{unit}'


def drift_markdown(report: Dict[str, Any], drift: DriftConfig) -> str:
    """report.md of a drift experiment."""
    seeds = report['seeds']
    lines = [f'# Drift scenario: {len(seeds)} seed(s) {seeds}', '',
             f'theta schedule (delta from theta*): {drift.schedule}; runs of '
             f'{drift.duration:g} s; recovery: the 5-s moving tracking cost back within '
             f'{RECOVERY_FACTOR}x the true-model NMPC\'s (told theta at every step).', '',
             '| method / mode | recovery, median (worst) | cost after / NMPC, median (worst) '
             '| cost before / NMPC, median | after / none (paired): worse on, worst, geomean '
             '| adaptations per run | models refused (by kind) | compute per adaptation, '
             'median | escapes |', '|---|---|---|---|---|---|---|---|---|']
    for name, row in report['table'].items():
        rec, after, before = row['recovery_s'], row['ratio_after'], row['ratio_before']
        counts = [c for c in row['adaptations'] if c is not None]
        compute = _fmt(np.median(row['compute_s']) if row['compute_s'] else None, ' s', '-')
        kinds = row.get('refusal_kinds') or {}
        refused = f'{sum(row.get("refusals") or [])}' + (
            ' (' + ', '.join(f'{k} {v}' for k, v in sorted(kinds.items())) + ')' if kinds else '')
        if name.endswith('/constant'):
            lines.append(f'| {name} (constant theta: spurious) | | | | | {sum(counts)} in '
                         f'{len(counts)} runs | {refused} | {compute} | {row["escapes"]} |')
            continue
        paired = row.get('vs_none')
        vs = '-' if not paired else (
            f'{paired["worse"]} of {len([v for v in paired["values"] if v is not None])}, '
            f'{_fmt(paired["worst"], none="-")}, {_fmt(paired["geomean"], none="-")}')
        lines.append(
            f'| {name} | {_fmt(rec["median"], " s")} ({_fmt(rec["worst"], " s")}) | '
            f'{_fmt(after["median"], none="-")} ({_fmt(after["worst"], none="escaped")}) | '
            f'{_fmt(before["median"], none="-")} | {vs} | '
            f'{np.median(counts) if counts else "-"} | {refused} | {compute} | '
            f'{row["escapes"]} |')
    lines += ['', 'Figures per seed: `seed_<s>/drift_<method>.png`.', '']
    return '\n'.join(lines)


__all__ = ['RunSignals', 'drift_runs', 'run_signals', 'squared_errors', 'moving_cost',
           'recovery_time', 'refusals', 'run_metrics', 'seed_drift_report',
           'drift_experiment_report', 'MOVING_WINDOW_S', 'RECOVERY_FACTOR']
