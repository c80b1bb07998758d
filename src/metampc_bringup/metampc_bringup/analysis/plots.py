"""PNG plots of a run (matplotlib, Agg backend): outputs against the reference, inputs, MPC
solve times, training loss. Each function returns the path written, or None when the run has
no data for that plot. No rclpy here.
"""
import os
from typing import List, Optional, Sequence, Tuple

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402

from metampc_bringup.analysis.metrics import Bounds, episodes, keys, reference_pairs  # noqa: E402
from metampc_bringup.analysis.run_series import RunSeries  # noqa: E402


def signal_labels(series: RunSeries, kind: str, n: int) -> List[str]:
    """'name [unit]' of each of the n inputs (kind 'input') or outputs ('output') as the
    plant's plant_info names them, else 'u[j]' / 'y[i]'."""
    info = series.plant_info or {}
    names, units = list(info.get(f'{kind}_names') or []), list(info.get(f'{kind}_units') or [])
    if len(names) != n:
        return [f"{'u' if kind == 'input' else 'y'}[{i}]" for i in range(n)]
    units = units if len(units) == n else [''] * n
    return [f'{name} [{unit}]' if unit else name for name, unit in zip(names, units)]


def _save(fig, path: str) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _finish_panels(fig, axes, xlabel: str, title: str, path: str) -> str:
    """Grid and legend on each panel of a column, the time axis below, the title above; save."""
    for ax in axes[:, 0]:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper right')
    axes[-1, 0].set_xlabel(xlabel)
    axes[0, 0].set_title(title)
    return _save(fig, path)


def _time_axis(series: RunSeries) -> Tuple[np.ndarray, str]:
    """Time of each output sample (shape [n]) and its axis label: a lockstep plant's header
    stamps are its sim time (n dt, never going back across resets), drawn as they are; a
    realtime plant's are wall-clock time, drawn from the first recorded sample."""
    stamp = series.outputs.stamp
    if (series.plant_info or {}).get('clock_mode') == 'lockstep':
        return stamp, 'plant time [s] (dotted: reset)'
    return (stamp - stamp[0] if stamp.size else stamp,
            'time since the first recorded sample [s] (dotted: reset)')


def _broken(values: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """`values` [n] as float with a NaN inserted where the episode changes, so a line is not
    drawn across a reset (pair with :func:`_broken` of the x values). Shape [n + resets]."""
    cuts = np.flatnonzero(np.diff(episode)) + 1
    return np.insert(np.asarray(values, dtype=float), cuts, np.nan)


def _mark_resets(ax, t: np.ndarray, episode: np.ndarray) -> None:
    """A dotted vertical line at the first sample of every episode after the first."""
    for i in np.flatnonzero(np.diff(episode)) + 1:
        ax.axvline(t[i], color='0.5', lw=0.8, ls=':')


def plot_outputs(series: RunSeries, path: str,
                 tracked: Optional[Sequence[int]] = None) -> Optional[str]:
    """Each output y_i against plant time, with the reference MPC tracked for the outputs in
    `tracked` (default: all); lines break at plant resets (dotted vertical lines)."""
    out = series.outputs
    if out.step.size == 0:
        return None
    tracked = range(series.n_y) if tracked is None else tracked
    oi, si = reference_pairs(out.step, series.status.step)
    (t, label), ep = _time_axis(series), episodes(out.step)
    n_y = series.n_y
    names = signal_labels(series, 'output', n_y)
    fig, axes = plt.subplots(n_y, 1, figsize=(9, 2.6 * n_y), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        ax.plot(_broken(t, ep), _broken(out.y[:, i], ep), label=names[i])
        if oi.size and i in tracked:
            ax.plot(_broken(t[oi], ep[oi]), _broken(series.status.y_ref0[si, i], ep[oi]),
                    '--', drawstyle='steps-mid', label='reference')
        _mark_resets(ax, t, ep)
        ax.set_ylabel(names[i])
    return _finish_panels(fig, axes, label, 'Plant outputs and reference', path)


def plot_inputs(series: RunSeries, path: str,
                u_bounds: Optional[Bounds] = None) -> Optional[str]:
    """Inputs against plant time, one panel per input: the applied input u_applied of sample
    k, held over (k-1, k], as a staircase, and each requested input (ControlInput answering
    step k) drawn at the end of the interval (k, k+1] it was meant for; its bounds dotted."""
    out, inp = series.outputs, series.inputs
    if out.u_applied.size == 0:
        return None
    (t, label), ep = _time_axis(series), episodes(out.step)
    n_u = out.u_applied.shape[1]
    names = signal_labels(series, 'input', n_u)
    fig, axes = plt.subplots(n_u, 1, figsize=(9, 3.2 * n_u), sharex=True, squeeze=False)
    # Output sample k+1 of the same episode, where the input answering step k was applied.
    applied_at = {key: i + 1 for i, key in enumerate(keys(out.step))
                  if i + 1 < out.step.size and ep[i + 1] == ep[i]}
    placed = [(applied_at[key], n) for n, key in enumerate(keys(inp.step))
              if key in applied_at]
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(_broken(t, ep), _broken(out.u_applied[:, j], ep), drawstyle='steps-pre',
                label='applied')
        if placed and j < inp.u.shape[1]:
            x, rows = (np.array(v) for v in zip(*placed))
            ax.plot(t[x], inp.u[rows, j], '.', ms=4, label='requested')
        if u_bounds is not None:    # this input's bounds (one number: every input's)
            for bound in u_bounds:
                values = np.atleast_1d(bound)
                ax.axhline(values[j if values.size > 1 else 0], color='k', lw=0.8, ls=':')
        _mark_resets(ax, t, ep)
        ax.set_ylabel(names[j])
    return _finish_panels(fig, axes, label, 'Inputs', path)


def plot_solve_times(series: RunSeries, path: str) -> Optional[str]:
    """OSQP solve time and whole tick time per MPC tick, ms."""
    st = series.status
    if st.step.size == 0:
        return None
    fig, ax = plt.subplots(figsize=(9, 3.2))
    ticks = np.arange(st.step.size)
    ax.plot(ticks, 1e3 * st.tick_time, lw=0.8, label='tick')
    solved = st.iterations >= 0
    ax.plot(ticks[solved], 1e3 * st.solve_time[solved], '.', ms=3, label='QP solve')
    ax.set_xlabel('MPC tick')
    ax.set_ylabel('time [ms]')
    ax.set_title('MPC solve times')
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper right')
    return _save(fig, path)


def plot_training_loss(series: RunSeries, path: str) -> Optional[str]:
    """Loss reported on `progress` against iteration: one panel per phase (meta-training's
    outer steps and adaptation's steps are different axes), one line per method."""
    p = series.progress
    finite = np.isfinite(p.loss) & (p.loss > 0)
    if not np.any(finite):
        return None
    # 'done' repeats each job's final loss at its last step: not a curve of its own.
    phases = sorted({phase for phase, ok in zip(p.phase, finite) if ok and phase != 'done'})
    if not phases:
        return None
    fig, axes = plt.subplots(len(phases), 1, figsize=(9, 3.2 * len(phases)), squeeze=False)
    for ax, phase in zip(axes[:, 0], phases):
        for method in sorted({m for a, m in zip(p.phase, p.method) if a == phase}):
            sel = np.array([(a, b) == (phase, method)
                            for a, b in zip(p.phase, p.method)]) & finite
            if np.any(sel):
                ax.semilogy(p.iteration[sel], p.loss[sel], '.-', ms=3, label=method)
        ax.set_xlabel(f'{phase} step')
        ax.set_ylabel('loss')
        ax.set_title(f'Training progress: {phase}')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(loc='upper right')
    return _save(fig, path)


def write_plots(series: RunSeries, out_dir: str,
                u_bounds: Optional[Bounds] = None,
                tracked: Optional[Sequence[int]] = None) -> List[str]:
    """All plots into `out_dir` (outputs.png, inputs.png, solve_times.png,
    training_loss.png); returns the paths written (a plot without data is left out)."""
    written = [
        plot_outputs(series, os.path.join(out_dir, 'outputs.png'), tracked),
        plot_inputs(series, os.path.join(out_dir, 'inputs.png'), u_bounds),
        plot_solve_times(series, os.path.join(out_dir, 'solve_times.png')),
        plot_training_loss(series, os.path.join(out_dir, 'training_loss.png')),
    ]
    return [p for p in written if p is not None]


def plot_variants(summary: dict, path: str) -> Optional[str]:
    """Per controller variant and method (retrack.summarise): steady offset per seed (left)
    and tracking cost / NMPC per seed (right, log scale; an escape drawn at the top)."""
    rows = [(name, method, row) for name, methods in summary.items()
            for method, row in methods.items()]
    if not rows:
        return None
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 0.45 * len(rows) + 1.5),
                                      sharey=True)
    labels = []
    top = max([r for _, _, row in rows for r in row['ratios'].values() if np.isfinite(r)]
              + [1.0]) * 2
    for i, (name, method, row) in enumerate(rows):
        labels.append(f'{name} {method}')
        offsets = np.array(list(row['offsets'].values()), dtype=float)
        ratios = np.array(list(row['ratios'].values()), dtype=float)
        jitter = np.linspace(-0.15, 0.15, len(ratios))
        left.plot(offsets, i + jitter, 'o', ms=4, alpha=0.7)
        right.plot(np.where(np.isfinite(ratios), ratios, top), i + jitter, 'o', ms=4,
                   alpha=0.7)
    left.set_yticks(range(len(rows)), labels)
    left.set_xlabel('steady offset: mean |y - r| over the last quarter of each set-point')
    right.set_xscale('log')
    right.axvline(1.0, color='k', lw=0.8)
    right.set_xlabel('tracking cost / true-model NMPC (escape: right edge)')
    for ax in (left, right):
        ax.grid(True, alpha=0.3)
        ax.invert_yaxis()
    fig.suptitle('Controller variants on the same recorded models, paired by seed')
    return _save(fig, path)


def plot_episodes(runs: dict, tracked: Sequence[int], path: str, title: str) -> str:
    """Closed-loop episodes of one seed ({variant: {method: closed_loop.Episode}}): the first
    tracked output against its reference, the first input, and the norm of the offset-free
    disturbance estimate, one line per (variant, method)."""
    fig, axes = plt.subplots(3, 1, figsize=(11, 8), sharex=True, squeeze=False)
    j = tracked[0] if tracked else 0
    ref_drawn = False
    for name, by_method in runs.items():
        for method, ep in by_method.items():
            k = np.arange(len(ep.y))
            label = 'NMPC (true model)' if method == 'nmpc' else f'{method}, {name}'
            style = dict(color='k', lw=1.5) if method == 'nmpc' else dict(lw=1)
            if not ref_drawn and len(ep.y_ref):
                axes[0, 0].plot(k[1:], ep.y_ref[:, j], 'k--', lw=0.8, label='reference')
                ref_drawn = True
            axes[0, 0].plot(k, ep.y[:, j], label=label, **style)
            axes[1, 0].plot(k, ep.u[:, 0], label=label, **style)
            if method != 'nmpc':
                norms = [float(np.linalg.norm(t.disturbance)) for t in ep.ticks]
                axes[2, 0].plot(k[:len(norms)], norms, label=label, **style)
    axes[0, 0].set_ylabel(f'y[{j}]')
    axes[1, 0].set_ylabel('u[0]')
    axes[2, 0].set_ylabel('|p| (offset-free estimate)')
    return _finish_panels(fig, axes, 'step', title, path)
