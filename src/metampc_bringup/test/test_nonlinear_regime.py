"""The nonlinear-regime study's pieces (nonlinear_regime): its loop, targets and collection."""
from dataclasses import replace
import time

import numpy as np
import pytest
import torch

from metampc_bringup.analysis.retrack import fly
from metampc_bringup.experiment_config import load
from metampc_bringup.studies import nonlinear_regime
from metampc_bringup.studies.nonlinear_regime import (
    closed_loop_record, collect, episode, experiment, meta_models, RegimeConfig, run, summary,
    targets, track)
from metampc_common.excitation import ExcitationConfig
from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_controller.references import make_reference
from metampc_learner.narx_learning import arx_model, NarxMetaConfig
from metampc_model.feature_narx import FeatureNarx, init_params, NarxShape
from metampc_model.normalisation import Normalisation
from metampc_plant.registry import get_family
from metampc_plant.simulator import PlantConfig, simulate

PLANT = PlantConfig(family='vanderpol', dt=0.1, substeps=10, u_min=(-1.0,), u_max=(1.0,))


def test_the_studys_loop_is_the_experiments_loop():
    """The study's episode (its own loop over a planner) against the experiment's controller
    core (retrack.fly) on the same NMPC: the same tracking cost, so the study's ratios divide
    by the experiment's yardstick."""
    exp = load(None, {'theta': [1.5], 'track_duration': 4.0})
    ctrl = exp.node_config('controller', 0)
    nmpc = fly(exp.node_parameters('controller', 0), exp.node_parameters('plant', 0), (1.5,),
               exp.track_x0, exp.track_steps())
    planner = Nmpc(NmpcConfig(**ctrl.mpc.shared(), dt=0.1, tail=ctrl.nmpc_tail),
                   get_family('vanderpol'), (1.5,))
    ref = make_reference(ctrl.reference_kind, **ctrl.reference_params)
    times = []
    start = time.perf_counter()
    ours = track(planner, PLANT, (1.5,), exp.track_x0, ref, exp.track_steps(), (0,),
                 times=times)
    wall = time.perf_counter() - start
    assert ours == pytest.approx(nmpc.tracking_cost([0]), rel=1e-9)
    # One solve time per step, within the episode's own time (the benchmarks' timing).
    assert len(times) == exp.track_steps() and min(times) > 0 and sum(times) < wall


def test_targets_are_the_given_thetas_by_seed_or_each_seeds_draw():
    given = targets(RegimeConfig(thetas=((1.5,), (2.0,)), seeds=(0, 1)))
    assert [(t.theta, t.seed) for t in given] == [((1.5,), 0), ((1.5,), 1), ((2.0,), 0),
                                                  ((2.0,), 1)]
    assert given[2].experiment.theta == [2.0]
    drawn = targets(RegimeConfig(seeds=(3, 4)))
    assert [t.theta for t in drawn] == [tuple(load(None).target_theta(s)) for s in (3, 4)]


def test_a_section_override_merges_into_the_section():
    cfg = experiment(RegimeConfig(experiment='config/pendulum.yaml',
                                  overrides={'controller': {'reference_values': [1.2, -1.2]}}))
    own = load('config/pendulum.yaml')
    assert cfg.controller['reference_values'] == [1.2, -1.2]
    assert cfg.controller['disturbance_gain'] == own.controller['disturbance_gain']


def test_collection_is_the_simulators_episode_cut_before_an_escape():
    exc = ExcitationConfig(u_min=(-1.0,), u_max=(1.0,))
    u, y = collect(exc, PLANT, (0.5,), (0.5, 0.0), 50, 3)
    assert u.shape == (50, 1) and y.shape == (50, 2)
    _, y_sim, _ = simulate(np.array([[0.5]]), np.array([[0.5, 0.0]]), u[None], PLANT)
    np.testing.assert_allclose(y_sim[0, 1:], y, atol=1e-12)   # u[k] produced y[k]
    # theta < 0 pushed outward escapes: the record stops before the first diverged sample
    u, y = collect(exc, PLANT, (-3.0,), (2.5, 2.5), 400, 0)
    assert len(y) < 400 and np.all(np.isfinite(y))


def test_the_summary_gives_median_worst_escapes_and_the_paired_claim():
    rows = [dict(model=m, cost=c, ratio=c / 2.0, heldout=h, heldout_loop=10 * h)
            for m, c, h in [('imaml', 2.0, 1e-3), ('arx', 4.0, 1e-2), ('imaml', 3.0, 2e-3),
                            ('arx', 2.5, 3e-2), ('imaml', float('inf'), 3e-3),
                            ('arx', 9.0, 5e-2)]]
    lines = summary(rows)
    assert lines[2] == '| imaml | 1.500 | inf | 1/3 | 2.00e-03 | 2.00e-02 |'
    assert lines[3] == '| arx | 2.000 | 4.500 | 0/3 | 3.00e-02 | 3.00e-01 |'
    assert lines[4].startswith('\nimaml < arx (paired): 1/3; median ratio 1.2')


def test_the_cache_gives_back_the_same_meta_model_and_keys_on_its_settings(tmp_path):
    config = RegimeConfig(seeds=(0,), features=2, hidden=(3,),
                          meta=NarxMetaConfig(iterations=2, batch_size=2, windows=4))
    said = []
    first = meta_models(config, said.append, str(tmp_path))['imaml']
    again = meta_models(config, said.append, str(tmp_path))['imaml']
    assert said[0].startswith('meta-trained') and said[1].startswith('meta-model imaml')
    for name, value in first.params.items():
        assert torch.equal(value, again.params[name])
    other = RegimeConfig(seeds=(0,), features=2, hidden=(3,),
                         meta=NarxMetaConfig(iterations=3, batch_size=2, windows=4))
    meta_models(other, said.append, str(tmp_path))
    assert said[2].startswith('meta-trained') and len(list(tmp_path.iterdir())) == 2


def test_a_stopped_study_resumes_from_the_rows_it_kept(tmp_path, monkeypatch):
    """Each target's rows are kept in the cache and read back, not flown again; fails on a
    key that leaves out the seed (the second target would get the first's rows) or on rows
    not kept."""
    config = RegimeConfig(seeds=(0, 1), thetas=((1.5,),), features=2, hidden=(3,),
                          oracle=False, overrides={'track_duration': 3.0},
                          meta=NarxMetaConfig(iterations=2, batch_size=2, windows=4))
    first = run(config, print, str(tmp_path))
    assert len(list(tmp_path.glob('rows_*.json'))) == 2

    def flown(*args):
        raise AssertionError('a kept target was flown again')
    monkeypatch.setattr(nonlinear_regime, 'target_rows', flown)
    again = run(config, print, str(tmp_path))
    assert [r['seed'] for r in again] == [0, 0, 1, 1]
    assert again == first
    with pytest.raises(AssertionError, match='flown again'):   # another target: not kept
        run(replace(config, seeds=(2,)), print, str(tmp_path))
    with pytest.raises(AssertionError, match='flown again'):   # other settings: not kept
        run(replace(config, closed_loop=0.5), print, str(tmp_path))


def test_the_lags_are_the_familys_learner_narx_order():
    """The study's p is the experiment's learner ``narx_order`` (the pendulum's and
    Duffing's 1, van der Pol's default 2) unless given; fails on a study that fixes p = 2 and
    on a Duffing configuration with p = 2 (first-order MAML's spurious unstable mode there:
    docs/studies/2026-12-08-duffing-regime.md)."""
    tiny = dict(seeds=(0,), features=2, hidden=(3,),
                meta=NarxMetaConfig(iterations=1, batch_size=2, windows=4))
    pend = RegimeConfig(experiment='config/pendulum.yaml', **tiny)
    assert load('config/pendulum.yaml').node_config('learner', 0).narx.order == 1
    assert load('config/duffing.yaml').node_config('learner', 0).narx.order == 1
    assert meta_models(pend, print)['imaml'].shape.order == 1
    assert meta_models(RegimeConfig(**tiny), print)['imaml'].shape.order == 2
    assert meta_models(RegimeConfig(order=3, **tiny), print)['imaml'].shape.order == 3


def test_the_pendulums_second_lags_fit_a_mode_its_plant_does_not_have():
    """Why the pendulum's p is 1 (docs/studies/2026-12-08-pendulum-lags.md): its outputs are
    its state, so the second lags are redundant in the one-step equations and the least
    squares sets them by the noise: on validation seed 109's 300 samples ARX(2) has an
    eigenvalue 1.021 (unstable; 1.076 through the normal equations, where its MPC tracked at
    2.8x the NMPC) where the plant's are exp(-b dt / (2 m l^2)) = 0.9994 and ARX(1)'s 0.9995
    (it tracked at 1.0x)."""
    tgt = targets(RegimeConfig(experiment='config/pendulum.yaml', seeds=(109,)))[0]
    plant = tgt.plant()
    records = [collect(tgt.controller().excitation, plant, tgt.theta,
                       tgt.experiment.collect_x0, 300, 109)]
    m, length, b = tgt.theta
    true = np.exp(-b * plant.dt / (2 * m * length ** 2))
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    radius = {}
    for p in (1, 2):
        shape = NarxShape(1, 2, p, 0, ())
        arx = arx_model(FeatureNarx(shape, norm, init_params(shape, 0)), records)
        lin = arx.linearise(arx.state(np.zeros((p, 1)), np.zeros((p, 2))), np.zeros(1))
        radius[p] = np.abs(np.linalg.eigvals(np.asarray(lin.A))).max()
    assert radius[1] == pytest.approx(true, abs=1e-3)
    assert radius[2] > 1.01


class _Constant:
    """A stand-in planner that always asks for the same input."""

    def __init__(self, u, horizon=3):
        self.u, self.config = np.array(u, float), type('C', (), {'horizon': horizon})()

    def reset(self):
        pass

    def solve(self, state, u, r, y, k):
        return type('S', (), {'u': self.u})()


def test_an_episodes_record_is_what_the_plant_did_with_the_exploration_inside_the_bounds():
    """u[k] is the planner's input plus the exploration, clipped to the bounds, and produced
    y[k]; fails on an exploration added after the clip (inputs beyond the bounds) or left
    out, and on a record shifted by one sample."""
    explore = np.linspace(-1.0, 1.0, 30)[:, None]
    ref = make_reference('setpoint_sequence', n_y=2, outputs=(0,), setpoints=(0.5,),
                         segment=10.0)
    cost, (u, y) = episode(_Constant([0.6]), PLANT, (1.0,), (0.5, 0.0), ref, 30, (0,),
                           explore=explore)
    np.testing.assert_allclose(u, np.clip(0.6 + explore, -1.0, 1.0))
    _, y_sim, _ = simulate(np.array([[1.0]]), np.array([[0.5, 0.0]]), u[None], PLANT)
    np.testing.assert_allclose(y, y_sim[0, 1:], atol=1e-9)
    assert cost == pytest.approx(np.sum((y[:, 0] - 0.5) ** 2))
    plain = episode(_Constant([0.6]), PLANT, (1.0,), (0.5, 0.0), ref, 30, (0,))
    np.testing.assert_allclose(plain[1][0], 0.6)
    assert plain[0] == track(_Constant([0.6]), PLANT, (1.0,), (0.5, 0.0), ref, 30, (0,))


FAR = {'controller': {'reference_values': [1.2, -0.8, 0.4, -1.2]}}


def test_the_closed_loop_record_visits_every_set_point_within_its_samples():
    """The far-from-rest pendulum's 4 set-points (5 s each in the tracking run) in 120
    samples (6 s): the segments shortened to 30 samples each, so each quarter of the record
    ends nearest its own set-point; fails on the tracking run's segments (the first two
    only)."""
    tgt = targets(RegimeConfig(experiment='config/pendulum.yaml', thetas=((0.5, 0.5, 0.05),),
                               seeds=(100,), overrides=FAR))[0]
    recs = [collect(tgt.controller().excitation, tgt.plant(), tgt.theta,
                    tgt.experiment.collect_x0, 150, 100)]
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    shape = NarxShape(1, 2, 2, 0, ())
    model = arx_model(FeatureNarx(shape, norm, init_params(shape, 0)), recs)
    u, y = closed_loop_record(model, tgt, 120, 0.0)
    assert u.shape == (120, 1) and y.shape == (120, 2)
    points = np.array([1.2, -0.8, 0.4, -1.2])
    for i, quarter in enumerate(np.split(y[:, 0], 4)):
        assert np.argmin(np.abs(quarter[15:].mean() - points)) == i


def test_the_closed_loop_share_is_taken_from_the_target_samples_not_added(monkeypatch):
    """With closed_loop 0.3 of 100 samples: 70 collected open loop, then per model (the
    method's and the ARX's) 30 in closed loop by the model fitted to those 70, and every
    model fitted again on the 100; fails on a study that collects 100 open loop and adds the
    closed-loop part."""
    import metampc_bringup.studies.nonlinear_regime as study
    seen = {'open': [], 'closed': [], 'fitted': []}
    real_collect, real_closed = study.collect, study.closed_loop_record
    real_adapt, real_arx = study.adapt, study.arx_model

    def counted_fit(real):
        def fit(meta, records, *args):
            seen['fitted'].append(sum(len(y) for _, y in records))
            return real(meta, records, *args)
        return fit

    def counted_collect(exc, plant, theta, x0, samples, seed):
        if seed < 10_000:
            seen['open'].append(samples)
        return real_collect(exc, plant, theta, x0, samples, seed)

    def counted_closed(model, tgt, samples, exploration):
        seen['closed'].append(samples)
        return real_closed(model, tgt, samples, exploration)

    monkeypatch.setattr(study, 'collect', counted_collect)
    monkeypatch.setattr(study, 'closed_loop_record', counted_closed)
    monkeypatch.setattr(study, 'adapt', counted_fit(real_adapt))
    monkeypatch.setattr(study, 'arx_model', counted_fit(real_arx))
    config = RegimeConfig(thetas=((1.0,),), seeds=(0,), features=2, hidden=(3,),
                          meta=NarxMetaConfig(iterations=1, batch_size=2, windows=4),
                          oracle=False, closed_loop=0.3,
                          overrides={'target_samples': 100, 'track_duration': 3.0})
    rows = study.run(config, log=lambda line: None)
    assert seen == {'open': [70], 'closed': [30, 30], 'fitted': [70, 100, 70, 100]}
    assert [r['model'] for r in rows] == ['imaml', 'arx']
    # the error where the controller operates is scored on the NMPC's episode, not the
    # open-loop held-out samples
    assert all(np.isfinite(r['heldout_loop']) and r['heldout_loop'] != r['heldout']
               for r in rows)
    with pytest.raises(ValueError):
        RegimeConfig(closed_loop=1.0)
