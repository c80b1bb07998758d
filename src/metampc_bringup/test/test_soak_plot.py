"""The soak's figure on a timeline built by hand: it is written, as a PNG."""
from metampc_bringup.soak.soak_metrics import deadlines
from metampc_bringup.soak.soak_plot import plot_soak


def test_figure_of_a_short_timeline(tmp_path):
    t0, period = 10**9, 10**7          # y every 10 ms from 1 s
    ys = [(t0 + k * period, k, 0.01 * k) for k in range(300)]
    us = [(t + 10**6, k, 0.01 * (k + 1), 1) for t, k, _ in ys if k != 150]   # 150 unanswered
    statuses = [(t + 10**6, k, 1e-3, 2e-4, False) for t, k, _ in ys]
    samples = {'plant': [(t0 + s * 10**9, (70 + s) * 2**20, 0.1 * s) for s in range(4)]}
    path = str(tmp_path / 'soak.png')
    plot_soak(path, ys, us, statuses, samples, deadlines(ys, us, t0 + 10**9), t0, 10**9)
    with open(path, 'rb') as f:
        assert f.read(8) == b'\x89PNG\r\n\x1a\n'
