"""The inner-steps sweep (metampc_bringup.studies.sweep, scripts/sweep_inner_steps.py): the
same budget for every (method, M), resuming from the cache without running anything again, the
summary statistics against hand computations, and exit status 2 on bad arguments."""
from dataclasses import asdict, replace
import hashlib
import importlib.util
import json
import math
import os
from pathlib import Path
import warnings

import pytest

from metampc_bringup.experiment_config import load
from metampc_bringup.orchestration.cluster import ClusterSpec
from metampc_bringup.studies.learning_setup import Job, settings_from, TEST_HELDOUT_SAMPLES
from metampc_bringup.studies.study_jobs import study_cluster
from metampc_bringup.analysis.paired_stats import median_ci
from metampc_bringup.studies.sweep import (ADAPT_LRS, estimate_cpu_s, evaluation_jobs, GRIDS,
                                           measured_run, paired, Plan, summarise, sweep,
                                           SweepError, tune_jobs, UNROLLED_MAX_M, winners)

ROOT = Path(__file__).resolve().parents[3]


def _tune_result(job: Job, score: float) -> dict:
    return {'method': job.method, 'index': job.index, 'hyper': job.hyper, 'score': score,
            'best_lr': 0.2}


def test_every_method_and_m_gets_the_same_budget():
    experiment = load(str(ROOT / 'config' / 'default.yaml'))
    plan = Plan()
    jobs = tune_jobs(experiment, plan)
    cells = {(j.method, j.hyper['inner_steps']) for j in jobs}
    assert cells == {(m, k) for m in ('imaml', 'maml') for k in (1, 5, 10, 25, 50)} | {
        ('maml_unrolled', k) for k in (1, 5, 10)}
    for cell in cells:
        mine = [j for j in jobs if (j.method, j.hyper['inner_steps']) == cell]
        assert len(mine) == len(GRIDS['imaml']) == 4
        assert {(j.iterations, j.lrs, j.stage, j.source_seed) for j in mine} == {
            (100, ADAPT_LRS, 'tune', 1000)}
        assert all(j.target_theta is None for j in mine)
    assert all(j.hyper['inner_steps'] <= UNROLLED_MAX_M for j in jobs
               if j.method == 'maml_unrolled')
    # lr_outer stays at the experiment's tuned value; unrolled MAML takes first-order MAML's.
    tuned = {m: experiment.meta_train[m]['lr_outer'] for m in ('imaml', 'maml')}
    assert {j.hyper['lr_outer'] for j in jobs if j.method == 'imaml'} == {tuned['imaml']}
    assert {j.hyper['lr_outer'] for j in jobs if j.method != 'imaml'} == {tuned['maml']}
    assert {j.hyper['cg_steps'] for j in jobs if j.method == 'imaml'} == {5}

    # The winner of each cell (lowest score; inf = failed) goes to every test seed.
    results = [_tune_result(j, math.inf if j.index == 0 else 1.0 / (1 + j.index))
               for j in jobs]
    best = winners(results)
    assert len(best) == len(cells) and all(w['index'] == 3 for w in best.values())
    tests = evaluation_jobs(experiment, plan, best)
    for cell in cells:
        mine = [j for j in tests if (j.method, j.hyper['inner_steps']) == cell]
        assert [j.source_seed for j in mine] == [0, 1, 2, 3, 4]
        assert all(j.iterations == 300 and j.lrs == (0.2,) and j.stage == 'test'
                   and j.heldout_samples == TEST_HELDOUT_SAMPLES
                   and j.target_theta == experiment.target_theta(j.source_seed) for j in mine)


def test_default_budget_fits_two_hours_on_two_cores():
    estimate = estimate_cpu_s(Plan())
    assert estimate['total'] == pytest.approx(12570, rel=0.01)     # docs/sweep.md's
    assert estimate['total'] / 2 < 2 * 3600


def test_old_jobs_keep_their_cache_key():
    settings = settings_from(str(ROOT / 'config' / 'default.yaml'), 2, 20)
    job = Job('imaml', 3, {'inner_steps': 5}, 150, (0.1, 0.2), 'search')
    fields = {k: v for k, v in asdict(job).items()
              if k not in ('target_theta', 'heldout_samples', 'prune_above')}
    blob = json.dumps([fields, repr(settings)], sort_keys=True, default=str)
    assert job.key(settings) == hashlib.sha256(blob.encode()).hexdigest()[:20]
    assert replace(job, target_theta=0.1).key(settings) != job.key(settings)
    assert replace(job, prune_above=(math.nan, 0.2)).key(settings) != job.key(settings)


def test_median_and_bootstrap_interval_by_hand():
    # Two values: resampled medians are 1 (p 1/4), 2 (1/2), 3 (1/4): the 2.5 % and 97.5 %
    # points are 1 and 3.
    assert median_ci([1.0, 3.0]) == (2.0, 1.0, 3.0)
    assert median_ci([5.0, 5.0, 5.0]) == (5.0, 5.0, 5.0)
    # Five values: the resampled median is the smallest one when 3 of the 5 draws are, with
    # p = 10 (1/5)^3 (4/5)^2 + 5 (1/5)^4 (4/5) + (1/5)^5 = 0.058 > 0.025, the largest alike.
    assert median_ci([4.0, 1.0, 100.0, 2.0, 3.0]) == (3.0, 1.0, 100.0)
    # A failed run (inf) stays the worst value, never NaN.
    assert median_ci([1.0, math.inf]) == (math.inf, 1.0, math.inf)
    median, low, high = median_ci([0.5])
    assert median == 0.5 and math.isnan(low) and math.isnan(high)


def _test_run(method, m, seed, losses, s_per_step, rss):
    adapt = [{'lr': 0.2, 'heldout_at': {str(k): [v] for k, v in zip((0, 1, 5, 20), losses)}}]
    return {'method': method, 'hyper': {'inner_steps': m}, 'source_seed': seed,
            'adapt': adapt if losses else [], 's_per_step': s_per_step, 'meta_seconds': 3.0,
            'peak_rss_mb': rss, 'rss_before_meta_mb': 300.0}


def test_summary_and_paired_comparison_by_hand():
    plan = Plan(methods=('imaml', 'maml'), ms=(5,), seeds=(0, 1, 2))
    runs = [_test_run('imaml', 5, 0, [1.0, 0.9, 0.5, 0.1], 0.3, 500.0),
            _test_run('imaml', 5, 1, [2.0, 1.8, 1.0, 0.4], 0.5, 520.0),
            _test_run('imaml', 5, 2, [4.0, 3.6, 2.0, 0.2], 0.4, 510.0),
            _test_run('maml', 5, 0, [1.0, 1.0, 1.0, 0.2], 0.2, 480.0),
            _test_run('maml', 5, 1, [], 0.2, 490.0),
            _test_run('maml', 5, 2, [2.0, 2.0, 2.0, 0.8], 0.1, 470.0)]
    best = {('imaml', 5): {'index': 1, 'hyper': {}, 'best_lr': 0.2, 'score': 0.1}}
    imaml, maml = summarise(plan, best, runs)
    assert imaml['seeds'] == [0, 1, 2] and imaml['failed'] == 0
    assert imaml['heldout']['20']['values'] == [0.1, 0.4, 0.2]
    assert imaml['heldout']['20']['median'] == 0.2 and imaml['heldout']['0']['median'] == 2.0
    assert imaml['s_per_step'] == 0.4 and imaml['peak_rss_mb'] == 510.0
    assert imaml['peak_rss_mb_max'] == 520.0 and imaml['winner']['index'] == 1
    assert maml['failed'] == 1 and maml['winner'] is None
    assert maml['heldout']['20']['values'] == [0.2, math.inf, 0.8]
    assert maml['heldout']['20']['median'] == 0.8
    k20 = [c for c in paired(plan, [imaml, maml]) if c['K'] == 20][0]
    # iMAML / MAML per seed: 0.5, 0 (inf), 0.25: lower on all three, median ratio 0.25.
    assert (k20['a'], k20['b'], k20['M'], k20['n'], k20['holds']) == ('imaml', 'maml', 5, 3, 3)
    assert k20['median_ratio'] == pytest.approx(0.25)


class RefusingClient:
    """A dask client that fails the test if anything is submitted."""

    def submit(self, *args, **kwargs):
        raise AssertionError('a cached run was started again')


def test_tiny_sweep_on_two_workers_then_resumes_without_running_anything(
        tmp_path, tiny_config, direct, untimed):
    """Its runs are those of direct calls (the process pool's before), each in a fresh
    process of its own (its peak RSS)."""
    config = tiny_config
    out = str(tmp_path / 'out')
    plan = Plan(('maml',), (1,), (0,), iterations=2, tune_iterations=2, thetas=1,
                adapt_steps=5, heldout_samples=100)
    with study_cluster(ClusterSpec(2)) as client:
        first = sweep(client, str(config), plan, out, 2)
    assert len(first['tune_runs']) == 4 and len(first['test_runs']) == 1
    assert len(os.listdir(os.path.join(out, 'cache'))) == 5
    for run in first['test_runs']:
        assert run['heldout_samples'] == 100 and run['peak_rss_mb'] > 0
        assert set(run['adapt'][0]['heldout_at']) == {'0', '1', '5'}
    for name in ('sweep.json', 'report.md', 'loss_vs_M.png', 'memory_vs_M.png'):
        assert os.path.getsize(os.path.join(out, name)) > 0
    experiment, settings = load(str(config)), settings_from(str(config), 1, 5)
    tuned = tune_jobs(experiment, plan)
    assert [untimed(r) for r in first['tune_runs']] == [
        direct(settings, job, measured_run) for job in tuned]
    tested = evaluation_jobs(experiment, plan, winners(first['tune_runs']))
    assert [untimed(r) for r in first['test_runs']] == [
        direct(settings, job, measured_run) for job in tested]

    again = sweep(RefusingClient(), str(config), plan, out)
    assert again['summary'] == first['summary'] and again['sessions'][-1]['runs_done'] == 0
    assert len(again['sessions']) == 2
    with pytest.raises(SweepError, match='other settings'):
        sweep(RefusingClient(), str(config), replace(plan, iterations=3), out)


def _script():
    spec = importlib.util.spec_from_file_location(
        'sweep_inner_steps', ROOT / 'scripts' / 'sweep_inner_steps.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize('args', [
    ['--methods', 'imaml,reptile'], ['--ms', '0,5'], ['--ms', '1,x'], ['--seeds', '0'],
    ['--methods', 'maml_unrolled', '--ms', '25'], ['--out-is-a-file']])
def test_bad_arguments_exit_2(tmp_path, capsys, args, tiny_config):
    config = tiny_config
    out = str(tmp_path / 'out')
    if args == ['--out-is-a-file']:
        out, args = str(config), []
    assert _script().main(['--config', str(config), '--out', out, *args]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not os.path.exists(tmp_path / 'out')


def test_the_plots_take_a_log_axis_only_for_positive_values(tmp_path, monkeypatch):
    """A tiny run's time per step rounds to 0 s (and a loss could be 0): that axis stays
    linear, without matplotlib's 'no positive values' warning; positive values get a log
    axis."""
    import matplotlib.axes
    from metampc_bringup.studies.sweep import plot_loss, plot_memory
    scales, set_yscale = [], matplotlib.axes.Axes.set_yscale

    def recorded(ax, value, **kwargs):
        scales.append(value)
        return set_yscale(ax, value, **kwargs)
    monkeypatch.setattr(matplotlib.axes.Axes, 'set_yscale', recorded)

    def row(m, value):
        stat = {'median': value, 'ci_low': value, 'ci_high': value}
        return {'method': 'maml', 'M': m, 'peak_rss_mb': 300.0, 'rss_before_meta_mb': 200.0,
                's_per_step': value, 'heldout': {'0': stat, '20': stat}}
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        for value, log in ((0.0, False), (0.5, True)):
            scales.clear()
            plot_memory([row(1, value), row(5, value)], str(tmp_path / 'memory.png'))
            plot_loss([row(1, value), row(5, value)], str(tmp_path / 'loss.png'))
            assert scales == (['log'] * 3 if log else [])
