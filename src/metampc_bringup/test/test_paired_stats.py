"""Paired claims over seeds (metampc_bringup.analysis.paired_stats) and their place in the
experiment report's claims table, checked against answers computed independently here."""
import itertools
import json
import math
from typing import Dict, List

import numpy as np
import pytest
from scipy.stats import binom, wilcoxon

from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.analysis.experiment_report import _restore, claims, markdown
from metampc_bringup.analysis.paired_stats import format_claim, median_ci, paired_claim


def _exact_wilcoxon_p(d: List[float]) -> float:
    """Two-sided exact signed-rank p-value by enumerating all sign patterns (|d| distinct,
    no zeros)."""
    ranks = np.argsort(np.argsort(np.abs(d))) + 1
    t = ranks[np.asarray(d) > 0].sum()
    sums = [sum(r for r, s in zip(ranks, signs) if s)
            for signs in itertools.product((0, 1), repeat=len(d))]
    below, above = np.mean(np.array(sums) <= t), np.mean(np.array(sums) >= t)
    return min(1.0, 2 * min(below, above))


def test_p_value_is_the_exact_signed_rank_test():
    d = [-1.5, -0.3, 0.2, -2.1, -0.9, 0.6, -1.1, -3.0]
    b = [10.0 + i for i in range(len(d))]
    stats = paired_claim([x + y for x, y in zip(d, b)], b)
    assert stats['p_wilcoxon'] == pytest.approx(_exact_wilcoxon_p(d), rel=1e-12)
    assert stats['p_wilcoxon'] == pytest.approx(wilcoxon(d).pvalue, rel=1e-12)
    assert stats['n'] == 8 and stats['holds'] == 6 and stats['dropped'] == 0
    assert stats['median_diff'] == pytest.approx(-1.0)     # (-1.1 - 0.9) / 2


def test_equal_differences_give_that_value_as_interval():
    b = [1.0, 2.0, 3.0, 4.0, 8.0]
    stats = paired_claim([x - 0.5 for x in b], b)
    assert stats['median_diff'] == stats['ci_low'] == stats['ci_high'] == -0.5
    assert stats['supported'] and not stats['contradicted']
    assert stats['p_wilcoxon'] == pytest.approx(2 / 2 ** 5)     # all 5 of one sign


def test_clear_effect_is_supported():
    rng = np.random.default_rng(7)
    b = rng.uniform(0, 5, 20)
    a = b + rng.normal(-1.0, 0.1, 20)
    stats = paired_claim(a, b)
    assert stats['supported'] and not stats['contradicted']
    assert stats['ci_low'] <= stats['median_diff'] <= stats['ci_high'] < 0
    assert -1.1 < stats['median_diff'] < -0.9
    assert stats['holds'] == 20 and stats['p_wilcoxon'] < 1e-5
    # The other way round it is contradicted.
    assert paired_claim(b, a)['contradicted']


def test_no_effect_is_not_supported():
    b = np.arange(1.0, 11.0)
    d = np.array([-5.0, -4, -3, -2, -1, 1, 2, 3, 4, 5]) * 0.25     # exact in binary
    stats = paired_claim(b + d, b)
    assert not stats['supported'] and not stats['contradicted']
    assert stats['ci_low'] < 0 < stats['ci_high']
    assert stats['holds'] == 5 and stats['p_wilcoxon'] == pytest.approx(1.0)


def test_same_seed_same_interval():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=12), rng.normal(size=12)
    first, again = paired_claim(a, b, seed=5), paired_claim(a, b, seed=5)
    assert first == again
    assert paired_claim(a, b, seed=6)['median_diff'] == first['median_diff']


def test_pairs_with_a_missing_value_are_dropped():
    a, b = [1.0, 2.0, 3.5, 4.0, 0.5], [1.5, 3.0, 3.0, 4.5, 2.0]
    clean = paired_claim(a, b)
    stats = paired_claim(a + [math.nan, 1.0], b + [2.0, math.nan])
    assert stats['n'] == 5 and stats['dropped'] == 2
    assert {k: v for k, v in stats.items() if k != 'dropped'} == {
        k: v for k, v in clean.items() if k != 'dropped'}


@pytest.mark.parametrize('a, b', [([1.0], [2.0]), ([], []), ([1.0, math.nan], [2.0, 3.0])])
def test_fewer_than_two_pairs_give_no_test(a, b):
    stats = paired_claim(a, b)
    assert stats['n'] < 2
    assert stats['p_wilcoxon'] is None and stats['ci_low'] is None and stats['ci_high'] is None
    assert not stats['supported'] and not stats['contradicted']
    assert format_claim(stats).endswith('p = n/a; not supported')


def test_all_ties_give_no_p_value():
    stats = paired_claim([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    assert stats['p_wilcoxon'] is None and stats['median_diff'] == 0.0
    assert not stats['supported'] and not stats['contradicted']


def test_escaped_runs_rank_beyond_every_finite_difference():
    """inf (an escaped run) on one side: the largest difference, of its sign; on both: a
    tie. The test's p-value is that of any larger-than-all finite stand-in."""
    b = [2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    a = [1.0, 2.5, math.inf, 4.0, 5.5, math.inf]
    stats = paired_claim(a, b)
    stand_in = paired_claim([1.0, 2.5, 4.0 + 1e6, 4.0, 5.5, 7.0 + 1e6], b)   # tied too
    assert stats['p_wilcoxon'] == stand_in['p_wilcoxon']
    assert stats['holds'] == 4 and stats['median_diff'] == -0.5     # -1, -1, -.5, -.5, inf, inf
    assert stats['ci_high'] == 'inf'    # resamples with half or more escapes
    assert not stats['supported'] and not stats['contradicted']
    # Both escaped: a tie, difference 0, not in the test.
    both = paired_claim([math.inf, math.inf, 1.0, 2.0], [math.inf, 5.0, 3.0, 4.0])
    assert both['n'] == 4 and both['holds'] == 2
    assert both['median_diff'] == -1.0     # sorted: -2, -2, 0, inf
    assert both['p_wilcoxon'] == pytest.approx(wilcoxon([math.inf, -2.0, -2.0]).pvalue)
    # Always escaped: infinitely worse, contradicted; strict JSON keeps the sign.
    worse = paired_claim([math.inf] * 5, [1.0, 2.0, 3.0, 4.0, 5.0], log=True)
    assert worse['median_ratio'] == worse['ratio_ci_low'] == 'inf' and worse['contradicted']
    json.dumps(worse, allow_nan=False)
    assert format_claim(worse) == '0/5; median ratio inf [inf, inf]; p = 0.062; contradicted'


def test_log_ratios():
    b = np.geomspace(1e-4, 1e2, 9)      # seeds spanning orders of magnitude
    rng = np.random.default_rng(1)
    stats = paired_claim(b * rng.uniform(0.45, 0.55, 9), b, log=True)
    assert 0.45 < stats['median_ratio'] < 0.55
    assert stats['ratio_ci_low'] == pytest.approx(math.exp(stats['ci_low']))
    assert stats['ratio_ci_high'] == pytest.approx(math.exp(stats['ci_high']))
    assert stats['ratio_ci_high'] < 1
    assert stats['supported'] and stats['holds'] == 9
    with pytest.raises(ValueError):
        paired_claim([-1.0, 1.0], [1.0, 1.0], log=True)


def _exact_bootstrap_ranks(n: int, confidence: float):
    """1-based ranks in the sorted sample of the percentile-bootstrap interval of the median
    of n (odd) distinct values, from the exact bootstrap distribution: the resampled median is
    <= the j-th smallest value iff at least (n + 1) / 2 draws are, a Binomial(n, j / n) count."""
    cdf = binom.sf((n + 1) // 2 - 1, n, np.arange(1, n + 1) / n)
    tail = (1 - confidence) / 2
    return int(np.argmax(cdf >= tail)) + 1, int(np.argmax(cdf >= 1 - tail)) + 1


def test_interval_is_the_95_percent_percentile_bootstrap():
    """Pins the interval's confidence level (documented 95 %) against the exact bootstrap
    distribution of the median of 1001 distinct values (binomial, no resampling): each endpoint
    is the order statistic of the 2.5 % / 97.5 % quantile within one rank (the Monte Carlo
    error of 20000 resamples); a 90 % interval lies 5 ranks inside, a 99 % one 10 outside."""
    n = 1001
    rng = np.random.default_rng(11)
    b = rng.uniform(1.0, 5.0, n)
    a = b + rng.normal(0.3, 1.0, n)
    low, high = _exact_bootstrap_ranks(n, 0.95)
    assert (low, high) == (470, 532)
    assert _exact_bootstrap_ranks(n, 0.90) == (475, 527)

    def ranks(values, ci_low, ci_high):
        s = np.sort(values)
        out = [int(np.searchsorted(s, float(v))) + 1 for v in (ci_low, ci_high)]
        assert [s[r - 1] for r in out] == [float(ci_low), float(ci_high)]
        return out

    d = a - b
    for seed in (0, 1):
        stats = paired_claim(a, b, n_boot=20000, seed=seed)
        got_low, got_high = ranks(d, stats['ci_low'], stats['ci_high'])
        assert abs(got_low - low) <= 1 and abs(got_high - high) <= 1
        _, m_low, m_high = median_ci(a, n_boot=20000, seed=seed)
        got_low, got_high = ranks(a, m_low, m_high)
        assert abs(got_low - low) <= 1 and abs(got_high - high) <= 1
    # The ratio interval is the same order statistics of the log differences.
    ratio = paired_claim(np.exp(d), np.ones(n), n_boot=20000, log=True)
    got_low, got_high = ranks(np.log(np.exp(d)), ratio['ci_low'], ratio['ci_high'])
    assert abs(got_low - low) <= 1 and abs(got_high - high) <= 1


def _fake_seed_report(seed: int, rng: np.random.Generator) -> Dict:
    """A seed report with the fields claims() reads: iMAML half of MAML's losses and costs,
    supervised ten times MAML's and escaped on seed 2."""
    maml_final = float(rng.uniform(0.01, 1.0))
    curve = np.geomspace(1.0, 0.1, 21) * rng.uniform(0.5, 2.0)
    cost = float(rng.uniform(1.0, 3.0))
    methods = {
        'imaml': (0.5 * maml_final, 0.5 * curve, 0.5 * cost),
        'maml': (maml_final, curve, cost),
        'supervised': (None, 10 * curve, math.inf if seed == 2 else 10 * cost),
        'oracle': (None, None, 0.9 * cost),
        'nmpc': (None, None, 0.8 * cost)}
    out = {}
    for method, (final, losses, c) in methods.items():
        entry = {'tracking': {'escaped': c == math.inf,
                              'tracking': {'cost': c, 'rmse': math.sqrt(c / 100)}}}
        if final is not None:
            entry['meta_train'] = {'final_loss': final}
        if losses is not None:
            entry['adapt'] = {'loss_curve': losses.tolist()}
        out[method] = entry
    return {'seed': seed, 'theta': 0.1 * seed, 'methods': out}


def test_claims_table_has_statistics():
    rng = np.random.default_rng(0)
    reports = [_fake_seed_report(seed, rng) for seed in range(5)]
    cl = claims(reports)
    a = cl['a_meta_loss_imaml_below_maml']
    assert a['holds'] == 5 and list(a['stats']) == ['imaml<maml']
    assert a['stats']['imaml<maml']['median_ratio'] == pytest.approx(0.5)
    assert a['stats']['imaml<maml']['supported']
    for k in ('0', '1', '5', '20'):
        stats = cl['b_adaptation_order'][k]['stats']
        assert list(stats) == ['imaml<maml', 'maml<supervised', 'imaml<supervised']
        assert stats['maml<supervised']['median_ratio'] == pytest.approx(0.1)
    costs = cl['c_tracking_cost_stats']
    assert list(costs) == ['imaml<maml', 'imaml<supervised', 'maml<supervised', 'imaml<nmpc',
                           'imaml<oracle', 'maml<nmpc', 'maml<oracle']
    assert costs['imaml<supervised']['holds'] == 5     # the escape counts, as the worst
    assert costs['maml<nmpc']['median_ratio'] == pytest.approx(1.25)
    assert costs['maml<nmpc']['contradicted']

    report = json_safe({
        'methods': ['imaml', 'maml', 'supervised', 'oracle', 'nmpc'],
        'seeds': [r['seed'] for r in reports], 'thetas': [r['theta'] for r in reports],
        'wall_time_s': 10.0, 'claims': cl, 'figures': [],
        'config': {k: {} for k in ('meta_train', 'adapt', 'learner', 'controller')},
        'per_seed': reports})
    json.dumps(report, allow_nan=False)
    text = markdown(_restore(report))
    assert '| claim | holds in | median ratio a/b [95 % CI] | Wilcoxon p | verdict |' in text
    assert ('| (a) final meta-training loss: iMAML < MAML | 5/5 | 0.5 [0.5, 0.5] | 0.062 | '
            'supported |') in text
    assert ('| (b) held-out target loss after 20 steps: iMAML < MAML < supervised | 5/5 | '
            '| | |') in text
    assert '| (b) after 20 steps: MAML < supervised | 5/5 | 0.1 [0.1, 0.1] | 0.062 |' in text
    assert '| (c) tracking cost: MAML vs NMPC | 0/5 | 1.25 [1.25, 1.25] | 0.062 | ' \
        'contradicted |' in text
    assert '| (c) tracking cost: iMAML < supervised | 5/5 |' in text
    assert '| (c) tracking cost of supervised (escaped 1/5) |' in text


def test_claims_at_steps_no_adaptation_ran_are_not_measured():
    """Adaptation with 5 steps: the K = 20 row says 'not measured', not '0/5' (failing)."""
    rng = np.random.default_rng(2)
    reports = [_fake_seed_report(seed, rng) for seed in range(5)]
    for r in reports:
        for entry in r['methods'].values():
            if 'adapt' in entry:
                entry['adapt']['loss_curve'] = entry['adapt']['loss_curve'][:6]
    report = json_safe({
        'methods': ['imaml', 'maml', 'supervised', 'oracle', 'nmpc'],
        'seeds': [r['seed'] for r in reports], 'thetas': [r['theta'] for r in reports],
        'wall_time_s': 10.0, 'claims': claims(reports), 'figures': [],
        'config': {k: {} for k in ('meta_train', 'adapt', 'learner', 'controller')},
        'per_seed': reports})
    text = markdown(_restore(report))
    assert ('| (b) held-out target loss after 20 steps | not measured (adaptation ran fewer '
            'steps) | | | |') in text
    assert '(b) after 20 steps:' not in text
    assert '| (b) held-out target loss after 5 steps: iMAML < MAML < supervised | 5/5 |' in text


def test_claims_leave_out_methods_not_run():
    rng = np.random.default_rng(1)
    reports = [_fake_seed_report(seed, rng) for seed in range(3)]
    for r in reports:
        del r['methods']['maml'], r['methods']['oracle']
    cl = claims(reports)
    assert cl['a_meta_loss_imaml_below_maml']['stats'] == {}
    assert list(cl['b_adaptation_order']['0']['stats']) == ['imaml<supervised']
    assert list(cl['c_tracking_cost_stats']) == ['imaml<supervised', 'imaml<nmpc']


def test_the_arx_baseline_is_compared_with_both_meta_methods():
    """With an 'arx' method (the linear baseline) the tracking costs and the large held-out
    losses get 'imaml < arx' and 'maml < arx'; markdown names it ARX."""
    rng = np.random.default_rng(3)
    reports = [_fake_seed_report(seed, rng) for seed in range(5)]
    for r in reports:
        maml = r['methods']['maml']['tracking']['tracking']['cost']
        r['methods']['arx'] = {'tracking': {'escaped': False, 'tracking': {
            'cost': 0.25 * maml, 'rmse': 0.1}}}
        for method, loss in (('imaml', 1.0), ('maml', 2.0), ('arx', 4.0)):
            r['methods'][method]['heldout'] = {'meta': None, 'adapted': loss}
    cl = claims(reports)
    costs = cl['c_tracking_cost_stats']
    assert list(costs)[-2:] == ['imaml<arx', 'maml<arx']
    assert costs['imaml<arx']['median_ratio'] == pytest.approx(2.0)   # 0.5 / 0.25
    assert costs['maml<arx']['contradicted']
    large = cl['b_heldout_large']['adapted']['stats']
    assert large['imaml<arx']['median_ratio'] == pytest.approx(0.25)
    assert large['imaml<arx']['supported'] and 'imaml<supervised' not in large
    report = json_safe({
        'methods': ['imaml', 'maml', 'supervised', 'oracle', 'arx', 'nmpc'],
        'seeds': [r['seed'] for r in reports], 'thetas': [r['theta'] for r in reports],
        'wall_time_s': 10.0, 'claims': cl, 'figures': [],
        'config': {k: {} for k in ('meta_train', 'adapt', 'learner', 'controller')},
        'per_seed': reports})
    text = markdown(_restore(report))
    assert '| (c) tracking cost: MAML < ARX | 0/5 | 4 [4, 4] | 0.062 | contradicted |' in text
    assert '| (c) tracking cost of ARX (escaped 0/5) |' in text
    assert '| (c) tracking cost of iMAML (escaped 0/5) |' in text
    # The learner's gain check flew the ARX in iMAML's place on seeds 1 and 3 (Adapt.fallback).
    for r in reports:
        r['methods']['imaml']['adapt'] = {'fallback': 'arx' if r['seed'] in (1, 3) else ''}
    cl = claims(reports)
    assert cl['c_tracking_cost']['imaml']['fallbacks'] == [1, 3]
    assert cl['c_tracking_cost']['maml']['fallbacks'] == []
    report['claims'] = cl
    text = markdown(_restore(json_safe(report)))
    assert ('| (c) tracking cost of iMAML (escaped 0/5; the ARX flew in its place on seeds '
            '[1, 3]) |') in text
    assert '| (c) tracking cost of MAML (escaped 0/5) |' in text


def test_the_feature_narx_rows_are_compared_with_the_arx_of_their_class_and_the_nssm():
    """Both model classes in one run (config/default.yaml): the narx_* rows against the ARX of
    their class on the large held-out set and in tracking, and in tracking against the
    NSSM's ARX, the NSSM's method of the same name and the NMPC; the paper's rows stay."""
    rng = np.random.default_rng(4)
    reports = [_fake_seed_report(seed, rng) for seed in range(5)]
    for r in reports:
        m, r['heldout'] = r['methods'], {'samples': 2000}
        cost = m['maml']['tracking']['tracking']['cost']
        for method, c, loss in (('arx', 1.0, 8.0), ('narx_imaml', 0.2, 1.0),
                                ('narx_maml', 0.4, 4.0), ('narx_arx', 0.25, 2.0)):
            m[method] = {'tracking': {'escaped': False,
                                      'tracking': {'cost': c * cost, 'rmse': 0.1}},
                         'heldout': {'meta': None, 'adapted': loss}}
        for method, loss in (('imaml', 0.5), ('maml', 16.0)):
            m[method]['heldout'] = {'meta': None, 'adapted': loss}
    cl = claims(reports)
    large = cl['b_heldout_large']['adapted']['stats']
    assert large['narx_imaml<narx_arx']['median_ratio'] == pytest.approx(0.5)
    assert large['narx_maml<narx_arx']['median_ratio'] == pytest.approx(2.0)
    assert large['imaml<arx']['median_ratio'] == pytest.approx(0.5 / 8.0)
    assert 'narx_imaml<arx' not in large      # another class's windows: not compared
    costs = cl['c_tracking_cost_stats']
    assert costs['narx_imaml<narx_arx']['median_ratio'] == pytest.approx(0.8)
    assert costs['narx_maml<narx_arx']['median_ratio'] == pytest.approx(1.6)
    assert costs['narx_imaml<arx']['median_ratio'] == pytest.approx(0.2)
    assert costs['narx_imaml<imaml']['median_ratio'] == pytest.approx(0.4)
    assert costs['narx_maml<nmpc']['median_ratio'] == pytest.approx(0.5)
    assert costs['imaml<maml']['median_ratio'] == pytest.approx(0.5)
    report = json_safe({
        'methods': ['narx_imaml', 'narx_maml', 'narx_arx', 'imaml', 'maml', 'supervised',
                    'oracle', 'arx', 'nmpc'],
        'seeds': [r['seed'] for r in reports], 'thetas': [r['theta'] for r in reports],
        'wall_time_s': 10.0, 'claims': cl, 'figures': [],
        'config': {k: {} for k in ('meta_train', 'adapt', 'learner', 'controller')},
        'per_seed': reports})
    text = markdown(_restore(report))
    assert ('| (b) adapted model on the large held-out set: NARX iMAML < NARX ARX | 5/5 | '
            '0.5 [0.5, 0.5] |') in text
    assert '| (c) tracking cost: NARX MAML < NARX ARX | 0/5 | 1.6 [1.6, 1.6] |' in text
    assert '| (c) tracking cost: NARX iMAML vs NMPC | 5/5 |' in text
    assert '| (c) tracking cost of NARX iMAML (escaped 0/5) |' in text
    assert '| (a) final meta-training loss: iMAML < MAML | 5/5 |' in text
    assert '| narx_imaml | n/a | 1 |' in text and '| imaml | n/a | 0.5 |' in text
