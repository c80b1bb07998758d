"""The soak's figure (matplotlib, Agg backend): controller tick and solve times, response time,
RSS growth and deadline misses over the run. Inputs as in :mod:`metampc_bringup.soak.soak_metrics`.
No rclpy here.
"""
from typing import Dict, Sequence

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402

from metampc_bringup.soak.soak_metrics import GOALS, observed_rate, responses  # noqa: E402


def plot_soak(path: str, ys: Sequence[tuple], us: Sequence[tuple], statuses: Sequence[tuple],
              samples: Dict[str, Sequence[tuple]], deadline: Dict[str, object], t0: int,
              warmup_ns: int) -> None:
    """Write the figure to `path` (PNG); deadline: the result of soak_metrics.deadlines, t0:
    receive time of the first y (monotonic ns), warmup_ns: the warm-up (marked)."""

    def sec(t):
        return (np.asarray(t, dtype=float) - t0) / 1e9

    fig, axes = plt.subplots(4, 1, figsize=(9, 11), sharex=True)
    st = np.array([(t, tick, solve) for t, _, tick, solve, _ in statuses]).reshape(-1, 3)
    axes[0].plot(sec(st[:, 0]), 1e3 * st[:, 1], '.', ms=1, label='tick')
    axes[0].plot(sec(st[:, 0]), 1e3 * st[:, 2], '.', ms=1, label='solve')
    axes[0].set_ylabel('controller, ms')
    axes[0].set_yscale('log')
    axes[0].legend(loc='upper right', markerscale=8)
    resp = responses(ys, us)
    if resp:
        r = np.array(resp, dtype=float)
        axes[1].plot(sec(r[:, 0]), r[:, 1] / 1e6, '.', ms=1)
    axes[1].axhline(1e3 / observed_rate(ys), color='r', lw=0.8, label='one period')
    axes[1].set_ylabel('y_k -> u_k seen here, ms')
    axes[1].set_yscale('log')
    axes[1].legend(loc='upper right')
    for name, series in samples.items():
        s = np.array([(t, b) for t, b, _ in series], dtype=float).reshape(-1, 2)
        base = s[s[:, 0] >= t0 + warmup_ns, 1]
        if base.size:
            axes[2].plot(sec(s[:, 0]), 100.0 * (s[:, 1] / base[0] - 1.0),
                         label=f'{name} ({base[0] / 2**20:.0f} MiB after warm-up)')
    axes[2].axhline(GOALS['rss_growth_pct'], color='r', lw=0.8, label='goal')
    axes[2].set_ylabel('RSS growth, %')
    axes[2].legend(loc='upper left')
    missed = sorted(deadline['arrived'][k] for k, o in deadline['outcome'].items()
                    if o in ('late', 'unanswered'))
    span = float(sec(ys[-1][0]))
    width = max(1.0, round(span / 60.0))
    axes[3].hist(sec(missed), bins=np.arange(0.0, span + width, width))
    axes[3].set_ylabel(f'deadline misses / {width:g} s')
    axes[3].set_xlabel('time since start, s')
    for ax in axes:
        ax.axvline(warmup_ns / 1e9, color='gray', ls=':', lw=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
