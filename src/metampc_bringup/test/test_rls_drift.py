"""The RLS drift study (studies/rls_drift.py): its schedules, the split of a run's cost at the
change, its rows for a CI-sized configuration, and the pairing by seed."""
from dataclasses import replace
import math
import os

import pytest

from metampc_bringup.analysis.retrack import fly
from metampc_bringup.studies import rls_drift
from metampc_bringup.studies.nonlinear_regime import experiment, meta_models, RegimeConfig
from metampc_learner.narx_learning import NarxMetaConfig

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
CI = os.path.join(ROOT, 'config', 'ci_drift.yaml')
TANK = os.path.join(ROOT, 'config', 'quadruple_tank.yaml')


def _regime(path):
    return RegimeConfig(experiment=path, seeds=(0,), features=4, hidden=(4,), oracle=False,
                        meta=NarxMetaConfig(iterations=2, batch_size=2, windows=4))


def test_the_schedules_are_the_experiments_or_toward_the_middle_of_the_prior():
    vdp = rls_drift.RlsDriftConfig(regime=_regime(CI))
    assert rls_drift.schedule(vdp, [0.5], 120, 0.1) == [6.0, 6.0, -0.5]     # drift.schedule
    tank = rls_drift.RlsDriftConfig(regime=_regime(TANK), centre_step=0.1)
    # g1, g2 ~ U(0.3, 0.8): each moves 0.1 toward 0.55 at half of 400 samples of 5 s
    assert rls_drift.schedule(tank, [0.62, 0.4], 400, 5.0) == pytest.approx(
        [1000.0, 1000.0, 0.52, 0.5])


def test_a_seed_gives_a_row_per_run_and_variant_with_the_cost_split_at_the_change():
    config = rls_drift.RlsDriftConfig(
        regime=_regime(CI), seeds=(0,),
        variants={'none': {}, 'rls': {'rls_forgetting': 0.95}})
    meta = meta_models(config.regime, lambda line: None)['imaml']
    rows = rls_drift.run_seed(config, 0, meta, log=lambda line: None)
    assert [(r['run'], r['variant']) for r in rows] == [
        ('drift', 'none'), ('drift', 'rls'), ('constant', 'none'), ('constant', 'rls')]
    none, rls = rows[0], rows[1]
    assert none['counts'] is None and rls['counts']['taken'] > 0
    for row in rows:
        assert row['ratio_after'] == pytest.approx(row['after'] / row['nmpc_after'])
    # the NMPC's costs, split at sample 60 (6 s), add up to its episode's tracking cost
    exp = experiment(config.regime)
    params = {**exp.node_parameters('plant', 0), 'theta_schedule': [6.0, 6.0, -0.5]}
    episode = fly(exp.node_parameters('controller', 0), params, [0.5], exp.track_x0, 120)
    assert none['nmpc_before'] + none['nmpc_after'] == pytest.approx(
        episode.tracking_cost(exp.tracked_outputs))
    assert none['nmpc_before'] == pytest.approx(sum(
        (episode.y[k, 0] - episode.y_ref[k - 1, 0]) ** 2 for k in range(1, 61)))
    # without the yardstick: the same costs, the ratios to it NaN
    alone = rls_drift.run_seed(replace(config, nmpc=False, constant=False), 0, meta,
                               log=lambda line: None)
    assert [r['after'] for r in alone] == [none['after'], rls['after']]
    assert all(math.isnan(r['ratio_after']) for r in alone)


def test_paired_divides_a_variant_by_the_baseline_seed_by_seed():
    rows = [dict(seed=s, run='drift', variant=v, after=c)
            for s, v, c in ((0, 'none', 2.0), (0, 'rls', 1.0), (1, 'none', 4.0),
                            (1, 'rls', 5.0), (2, 'rls', 1.0))]
    assert rls_drift.paired(rows, 'rls') == {0: 0.5, 1: 1.25}
    rows.append(dict(seed=3, run='drift', variant='rls', after=math.inf))
    rows.append(dict(seed=3, run='drift', variant='none', after=1.0))
    assert rls_drift.paired(rows, 'rls')[3] == math.inf
