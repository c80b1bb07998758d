"""The Cascaded Tanks benchmark's report: the summary over seeds, its tables and figures.

:func:`summary` gathers each seed's test-record figures (median, min, max) and the twin's
tracking (:func:`..analysis.retrack.summarise`: cost / NMPC); :func:`table` and
:func:`twin_table` print them as markdown (the published figures of PUBLISHED beside);
:func:`figure` and :func:`twin_figure` draw one seed's free runs on the test record and
tracking runs on the twin (matplotlib, Agg). No ROS.
"""
from typing import Dict, List, Sequence

import numpy as np

from metampc_bringup.analysis.retrack import summarise

# Published free-run simulation RMSE on the test record, volts, models fitted on all 1024
# estimation samples (Math. Probl. Eng. 2021, 6613425, Table 2; docs/real_data.md).
PUBLISHED = {'BLA': 0.7574, 'PNLSS-I': 0.4498, 'NLSS2': 0.3433}
COLOURS = {'imaml': 'C0', 'maml': 'C1', 'supervised': 'C2'}   # the twin figure's


def summary(reports: List[dict], nmpc: dict) -> dict:
    """Over the seeds: each model's test figures per fit (values by seed, median, min, max)
    and the twin's tracking (retrack.summarise: cost / NMPC by seed, median, worst, escapes)."""
    test: Dict[str, dict] = {}
    for report in reports:
        for r in report['rows']:
            key = f'{r["fit"]} {r["model"]}'
            row = test.setdefault(key, {'fit': r['fit'], 'model': r['model']})
            for name, value in r['test'].items():
                row.setdefault(name, []).append(value)
    for row in test.values():
        for key in ('simulation_rmse', 'prediction_rmse'):
            values = row[key]
            row[key] = {'values': values, 'median': float(np.median(values)),
                        'min': min(values), 'max': max(values)}
    return {'seeds': [r['seed'] for r in reports], 'test': list(test.values()),
            'twin': summarise({r['seed']: r['twin'] for r in reports}), 'nmpc': nmpc,
            'published': PUBLISHED}


def spread(figure: dict) -> str:
    """median (min..max) of a test figure over the seeds, volts (the value for one seed)."""
    if figure['min'] == figure['max']:
        return f'{figure["median"]:.4f}'
    return f'{figure["median"]:.4f} ({figure["min"]:.4f}..{figure["max"]:.4f})'


def table(result: dict) -> str:
    """The markdown table of the test figures (volts), median (min..max) over the seeds."""
    lines = ['| fitted on | model | simulation RMSE (V) | 10-step prediction RMSE (V) |',
             '|---|---|---|---|']
    for r in result['test']:
        lines.append(f"| estimation 0..{r['fit'] - 1} | {r['model']} | "
                     f"{spread(r['simulation_rmse'])} | {spread(r['prediction_rmse'])} |")
    for name, value in PUBLISHED.items():
        lines.append(f'| estimation 0..1023 (published) | {name} | {value:.4f} | |')
    return '\n'.join(lines)


def twin_table(result: dict) -> str:
    """The markdown table of the twin's tracking cost / the NMPC's (inf: escaped)."""
    seeds = result['seeds']
    lines = [f'| fitted on | model | cost / NMPC, seeds {", ".join(map(str, seeds))} | median | '
             'worst | escapes | refused | mean steady offset (V) |', '|---' * 8 + '|']
    for variant, methods in result['twin'].items():
        for method, row in methods.items():
            ratios = ', '.join(f'{row["ratios"][s]:.3g}' for s in seeds)
            lines.append(f'| estimation 0..{int(variant.split()[1]) - 1} | {method} | {ratios} | '
                         f'{row["median"]:.3g} | {row["worst"]:.3g} | {row["escapes"]} | '
                         f'{row["rejected"]} | {row["mean_offset"]:.3f} |')
    nmpc = result['nmpc']
    lines.append(f'| | NMPC (true model) | cost {nmpc["cost"]:.4g} | | | '
                 f'{int(nmpc["escaped"])} | | {np.mean(nmpc["offsets"]):.3f} |')
    return '\n'.join(lines)


def figure(path: str, yt: np.ndarray, sims: Dict[str, np.ndarray], ts: float,
           fits: Sequence[int], meta: Sequence[str]) -> None:
    """The test record's measured level (N,) and each model's free-run simulation, per fit of
    `fits` ('test <model> <n>' in `sims`; the meta methods `meta`); ts the sample time, s."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(fits), 1, figsize=(8, 5.5), sharex=True)
    t = np.arange(len(yt)) * ts
    for ax, n in zip(axes, fits):
        ax.plot(t, yt, 'k', lw=1.5, label='measured')
        for name in (*meta, 'supervised', 'ARX', 'grey-box'):
            ax.plot(t, sims[f'test {name} {n}'], lw=0.9, label=name)
        ax.set_ylabel('level (V)')
        ax.set_title(f'test record, free run; fitted on estimation samples 0..{n - 1}',
                     fontsize=9)
        ax.set_ylim(0, 12)
    axes[0].legend(fontsize=7, ncol=6, loc='upper left')
    axes[-1].set_xlabel('time (s)')
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def twin_figure(path: str, seed: int, runs: Dict[str, np.ndarray],
                nmpc: Dict[str, np.ndarray], ts: float, fits: Sequence[int],
                meta: Sequence[str]) -> None:
    """One seed's tracking runs on the twin, per fit of `fits` ('twin <method> <n> y|u' in
    `runs`; the meta methods `meta`): the level against the reference, and the pump voltage."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, len(fits), figsize=(9, 5), sharex=True,
                             gridspec_kw={'height_ratios': [2, 1]})
    t = np.arange(len(nmpc['y'])) * ts
    for col, n in enumerate(fits):
        top, bottom = axes[0, col], axes[1, col]
        for name in ('supervised', *meta, 'nmpc'):     # the NMPC on top
            run = nmpc if name == 'nmpc' else {
                part: runs[f'twin {name} {n} {part}'] for part in ('y', 'u')}
            style = {'color': 'k', 'lw': 1.0, 'label': 'NMPC'} if name == 'nmpc' else {
                'color': COLOURS[name], 'lw': 0.8, 'label': name,
                'alpha': 0.6 if name == 'supervised' else 1.0}
            top.plot(t, run['y'], **style)
            bottom.plot(t, run['u'], **style)
        top.plot(t[1:], nmpc['y_ref'], 'r--', lw=0.8, label='reference')
        top.set_title(f'twin, seed {seed}; NSSMs fitted on estimation 0..{n - 1}', fontsize=9)
        top.set_ylim(0, 11)
        bottom.set_xlabel('time (s)')
    axes[0, 0].set_ylabel('lower level (V)')
    axes[1, 0].set_ylabel('pump (V)')
    axes[0, 0].legend(fontsize=7, ncol=2, loc='lower left')
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt
