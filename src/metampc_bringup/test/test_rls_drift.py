"""The RLS drift study (studies/rls_drift.py): its schedules, the split of a run's cost at the
change, its rows for a CI-sized configuration, and the pairing by seed."""
from dataclasses import replace
import math
import os

import numpy as np
import pytest

from metampc_bringup.analysis.retrack import fly
from metampc_bringup.studies import rls_drift
from metampc_bringup.studies.nonlinear_regime import experiment, meta_models, RegimeConfig
from metampc_controller.adaptation_trigger import Request
from metampc_controller.controller_params import parse_params, PARAMETERS
from metampc_learner.narx_learning import adapt, NarxMetaConfig

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


def test_a_variant_with_adaptation_has_its_requests_answered_by_the_meta_models_fit():
    """CI drift (12 s, adapt_period 4 s of the configuration, loop_window 40): periodic requests
    at 4 and 8 s are answered in the loop, each by adapt(meta, the latest 40 samples): the row
    lists them and their rules, the flown model after the last is that fit (its head), and the
    variant's cost differs from none's. Fails where the answer fits the whole episode, or where
    a request is not answered."""
    config = rls_drift.RlsDriftConfig(
        regime=_regime(CI), seeds=(0,), constant=False, nmpc=False,
        variants={'none': {}, 'periodic': {'adaptation': 'periodic'}})
    meta = meta_models(config.regime, lambda line: None)['imaml']
    rows = rls_drift.run_seed(config, 0, meta, log=lambda line: None)
    none, periodic = rows
    assert none['requests'] == [] and periodic['requests'] == [40, 80]
    assert len(periodic['answers']) == 2 and periodic['after'] != none['after']
    # the answer by hand: one learner, one request at step 80 on samples 41..80
    seen = []

    class Core:
        model, n_u, n_y = None, 1, 2

        def offer(self, bundle, step):
            seen.append((bundle, step))

    Core.config = parse_params({name: spec.default for name, spec in PARAMETERS.items()})
    rules = []
    learner = rls_drift.answer_requests(meta, 1e-5, 40, rules)
    rng = np.random.default_rng(0)
    u, y = rng.uniform(-1, 1, (81, 1)), rng.uniform(-1, 1, (81, 2))
    learner(Core(), Request(80, 90, 'periodic', 1), u, y)
    by_hand = adapt(meta, [(u[41:], y[41:])], 1e-5)
    (bundle, step), = seen
    assert step == 80 and rules == [by_hand.rule] and bundle.version == 2
    assert np.allclose(bundle.predictor.head, by_hand.model.params['head'].numpy(), atol=1e-6)
