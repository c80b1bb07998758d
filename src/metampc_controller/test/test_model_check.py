"""The check a new model must pass before it flies (model_check.py; through the controller's
gate: ControllerCore.offer and its ticks).

Independent answers: the plant core's own data; a model linearised at the plant's theta
(good), the same model with its input matrix negated (it predicts the plant to move the
wrong way: bad), and persistence computed by hand.
"""
import dataclasses
import math

import numpy as np
import pytest

from metampc_controller.adaptation_trigger import TriggerConfig
from metampc_controller.controller_core import build_model, ControllerCore, TickResult
from metampc_controller.controller_params import ControllerConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_controller.model_check import check, ModelCheckConfig, n_step_error, warmup
from metampc_controller.model_gate import GateConfig, Outcome
from metampc_controller.mpc import MpcConfig
from metampc_model.predictor import NssmPredictor
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.plant_description import PlantDescription
from metampc_plant.simulator import Plant, PlantConfig

MPC = MpcConfig(time_limit=30.0)


def manual(theta=0.5, flip=False):
    config, norm, params = linearised_vdp_nssm(theta, 0.1, 10)
    if flip:
        params = dict(params, B=-params['B'])
    return DecodedWeights(config, norm, params)


def predictor(**kw) -> NssmPredictor:
    d = manual(**kw)
    return NssmPredictor(d.config, d.norm, d.params)


def plant_data(steps=200, seed=0):
    """Samples of the van der Pol plant (theta 0.5) under a random input held 0.5 s."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig(theta=(0.5,)))
    u = np.repeat(rng.uniform(-0.8, 0.8, steps // 5 + 1), 5)[:steps, None]
    y = np.empty((steps, 2))
    y[0] = plant.output()
    u[0] = 0.0
    for k in range(1, steps):
        y[k] = plant.step(u[k])
    return u, y


def test_n_step_error_of_persistence_by_hand():
    u, y = plant_data(60)
    scale = np.std(y, axis=0)
    e = n_step_error(lambda t: np.repeat(y[t:t + 1], 5, 0), y, 9, 5, 7, scale)
    starts = range(9, 60 - 5, 7)
    by_hand = np.mean([((y[t + k] - y[t]) / scale) ** 2 for t in starts for k in range(1, 6)])
    assert e == pytest.approx(by_hand, rel=1e-12)


def test_a_good_model_passes_a_bad_one_is_refused():
    u, y = plant_data()
    cfg = ModelCheckConfig()
    good, bad = predictor(), predictor(flip=True)
    first = check(good, None, u, y, MPC, cfg)              # against persistence
    assert first.ok and first.candidate < first.reference
    assert first.reason().startswith('check passed') and 'persistence' in first.reason()
    refused = check(bad, good, u, y, MPC, cfg)
    assert not refused.ok and refused.candidate > 1.25 * refused.reference
    assert refused.reason().startswith('check: its 20-step prediction error')
    assert 'of the model in use' in refused.reason()
    assert check(good, bad, u, y, MPC, cfg).ok            # better than the one in use
    short = check(bad, good, u[:25], y[:25], MPC, cfg)     # 25 < H + N + 1 = 31 samples
    assert short.ok and short.reason().startswith('unchecked: 25 samples') and math.isnan(
        short.candidate) and not short.scored


def test_a_model_the_check_must_refuse_is_refused_and_the_loop_goes_on():
    core = ControllerCore(ControllerConfig(reference_kind='setpoint',
                                           reference_params={'value': 0.5}, mpc=MPC,
                                           gate=GateConfig(model_check='all')))
    plant = Plant(PlantConfig(theta=(0.5,)))
    good = build_model(manual(), 1, 'manual', 'adapted', MPC, 1, 2)
    assert core.offer(good).outcome is Outcome.FLEW
    y, u = plant.output(), 0.0
    for k in range(200):
        if k == 100:    # a bad model arrives mid-run
            bad = build_model(manual(flip=True), 2, 'manual', 'adapted', MPC, 1, 2)
            event = core.offer(bad)
            assert event.outcome is Outcome.REFUSED
            assert event.reason.startswith('check: its 20-step prediction error')
        core.observe(k, [u], y)
        res = core.tick()
        assert res.model_version == 1 and res.solver_status == 'solved'
        u = float(res.u[0])
        y = plant.step([u])
    assert res.model_status == f'rejected: {event.reason}'
    assert abs(plant.output()[0] - 0.5) < 1e-2


def _ran_60_steps(gate: GateConfig, check_config: ModelCheckConfig = ModelCheckConfig()
                  ) -> ControllerCore:
    """A core with the good model in use after 60 steps of the plant (theta 0.5, set-point
    0.5), the gate and the check configured by `gate` and `check_config`."""
    core = ControllerCore(ControllerConfig(reference_kind='setpoint',
                                           reference_params={'value': 0.5}, mpc=MPC,
                                           gate=gate, model_check=check_config))
    core.offer(build_model(manual(), 1, 'manual', 'adapted', MPC, 1, 2))
    plant = Plant(PlantConfig(theta=(0.5,)))
    y, u = plant.output(), 0.0
    for k in range(60):
        core.observe(k, [u], y)
        u = float(core.tick().u[0])
        y = plant.step([u])
    return core


def test_a_late_answer_to_a_given_up_request_is_checked_too():
    """Under `requested`, an answer whose request was given up (it came after adapt_timeout)
    is still an answer to this controller's request: it is used from the next tick if it
    passes, so it must pass the check like a timely one."""
    core = _ran_60_steps(GateConfig())
    assert core.tuning.config.gate.model_check == 'requested'
    late = build_model(manual(flip=True), 2, 'manual', 'adapted', MPC, 1, 2)
    assert core.trigger.pending is None     # no request pending: any earlier one is over
    refused = core.offer(late, request_step=40)
    assert refused.outcome is Outcome.REFUSED and refused.reason.startswith(
        'check: its 20-step prediction error')
    unchecked = core.offer(late)
    assert unchecked.outcome is Outcome.FLEW and unchecked.verdict is None, (
        'a model naming no request is not checked under requested')


def test_history_snapshot_is_the_episode_oldest_first():
    core = ControllerCore(ControllerConfig())
    for k in range(5):
        core.observe(k, [float(k)], [k, -k])
    u, y = core.history.snapshot()
    assert u[:, 0].tolist() == [0, 1, 2, 3, 4] and y[:, 1].tolist() == [0, -1, -2, -3, -4]
    core.observe(0, [9.0], [9, 9])            # a plant reset: a new episode
    assert core.history.snapshot()[0].tolist() == [[9.0]]


def _tried_run(trial: int, candidate: DecodedWeights, flip_at: int = 10 ** 9,
               probation: int = 0, flip_until: int = 10 ** 9, steps: int = 100):
    """A lockstep core on the plant (theta 0.5) with the good model in use, periodic requests
    every 4 s (step 40, swap step 50), `candidate` answering the first one at step 45 (tried
    for `trial` samples, then on `probation`), and the plant's input negated from step
    `flip_at` to `flip_until` (a plant that changed at once: the flipped model is then the
    right one). Returns the tick results of steps 0..steps - 1, the answer's arrival event
    before that of step 45."""
    config = ControllerConfig(reference_kind='setpoint', reference_params={'value': 0.5},
                              mpc=MPC, trigger=TriggerConfig(adaptation='periodic',
                                                             adapt_period=4.0),
                              gate=GateConfig(model_check_trial=trial,
                                              model_check_probation=probation))
    core = ControllerCore(config)
    core.set_plant(PlantDescription('vanderpol', 0.1, (-1.0,), (1.0,), 2, True))
    core.offer(build_model(manual(), 1, 'manual', 'adapted', MPC, 1, 2))
    plant = Plant(PlantConfig(theta=(0.5,)))
    y, u, results = plant.output(), 0.0, []
    for k in range(steps):
        core.observe(k, [u], y)
        if k == 45:
            bundle = build_model(candidate, 2, 'manual', 'adapted', MPC, 1, 2)
            results.append(core.offer(bundle, 40))
        res = core.tick()
        results.append(res)
        u = float(res.u[0])
        y = plant.step([-u if flip_at <= k + 1 < flip_until else u])
    return results


def judged(ticks):
    """(step, outcome) of every verdict a tick took effect with."""
    return [(r.step, e.outcome) for r in ticks for e in r.events if e.verdict is not None]


def test_a_requested_answer_is_judged_on_its_trial_samples_alone():
    """The plant changes at the swap step (50) to the flipped model's: on the samples before,
    which the arrival check scores, the flipped model is wrong and is refused; on the trial's
    samples after the swap step it is right and flies at step 50 + trial exactly."""
    at_arrival = _tried_run(0, manual(flip=True), flip_at=50)
    assert at_arrival[45].outcome is Outcome.REFUSED
    assert at_arrival[45].reason.startswith('check: its 20-step prediction error')
    tried = _tried_run(25, manual(flip=True), flip_at=50)
    assert (tried[45].outcome, tried[45].start) == (Outcome.QUEUED, 50)    # nothing refused
    ticks = [r for r in tried if isinstance(r, TickResult)]
    assert [r.model_version for r in ticks] == [1] * 75 + [2] * 25
    assert judged(ticks) == [(75, Outcome.FLEW)] and ticks[75].model_status == 'ok'
    verdict = ticks[75].events[0].reason
    assert verdict.startswith('check passed') and 'its trial from step 50' in verdict and (
        '26 samples' in verdict)
    assert [r.request.step for r in ticks if r.request] == [40, 80]


def test_a_tried_answer_that_predicts_worse_is_refused_and_the_loop_goes_on():
    """A bad answer (flipped) on an unchanged plant: the model in use controls through the
    trial and after it, model_status says why, and the trigger asks again later."""
    ticks = [r for r in _tried_run(25, manual(flip=True)) if isinstance(r, TickResult)]
    assert {r.model_version for r in ticks} == {1}
    assert all(r.solver_status == 'solved' for r in ticks)
    assert judged(ticks) == [(75, Outcome.REFUSED)]
    assert ticks[75].events[0].reason.startswith('check: its 20-step prediction error')
    assert all(r.model_status == f'rejected: {ticks[75].events[0].reason}' for r in ticks[75:])
    assert [r.request.step for r in ticks if r.request] == [40, 80]


def test_a_flown_answer_that_predicts_its_own_loop_worse_is_reverted_and_the_loop_goes_on():
    """The plant is flipped during the trial only (steps 50-74): the flipped answer passes it
    and flies at 75 on probation; the plant is itself again, and on the 51 samples of the
    answer's own loop the model it replaced predicts better: at 125 that model (version 1)
    comes back, model_status says why, and the trigger asks again at once (its request was
    pending through the probation: none at 80 or 120)."""
    ticks = [r for r in _tried_run(25, manual(flip=True), flip_at=50, probation=50,
                                   flip_until=75, steps=150) if isinstance(r, TickResult)]
    assert [r.model_version for r in ticks] == [1] * 75 + [2] * 50 + [1] * 25
    assert judged(ticks) == [(75, Outcome.FLEW), (125, Outcome.REVERTED)]
    assert ticks[75].events[0].reason.startswith('check passed')
    verdict = ticks[125].events[0].reason
    assert verdict.startswith('check: its 20-step prediction error') and (
        'on 51 samples (its probation from step 75, on its own loop)' in verdict
        and verdict.endswith('of the model it replaced'))
    assert all(r.model_status == f'reverted: {verdict}' for r in ticks[125:])
    assert [r.request.step for r in ticks if r.request] == [40, 125]
    assert all(r.solver_status == 'solved' for r in ticks)


def test_a_flown_answer_that_stays_the_better_predictor_is_kept_after_its_probation():
    """The plant stays flipped from step 50: the flipped answer flies at 75 and is kept at
    125, the request answered then (the next one at once: its period has passed)."""
    ticks = [r for r in _tried_run(25, manual(flip=True), flip_at=50, probation=50,
                                   steps=150) if isinstance(r, TickResult)]
    assert [r.model_version for r in ticks] == [1] * 75 + [2] * 75
    assert judged(ticks) == [(75, Outcome.FLEW), (125, Outcome.KEPT)]
    assert ticks[125].events[0].reason.startswith('check passed')
    assert ticks[125].model_status == 'ok'
    assert [r.request.step for r in ticks if r.request] == [40, 125]


def linear_data(model: NssmPredictor, bias, steps=200, seed=0):
    """Samples of the manual model's own linear latent system (z_t = x_t, y = x) under a random
    input held 0.5 s, each y offset by the constant `bias` (n_y,): a sensor offset."""
    rng = np.random.default_rng(seed)
    latent = model.latent
    u = np.repeat(rng.uniform(-0.8, 0.8, steps // 5 + 1), 5)[:steps, None]
    u[0] = 0.0
    x = np.empty((steps, latent.n_z))
    x[0] = 0.0
    for k in range(1, steps):
        x[k] = latent.step(x[k - 1], u[k])
    return u, x @ latent.C.T + latent.d + np.asarray(bias)


def test_with_offset_free_each_model_is_scored_as_the_mpc_plans_with_it():
    """A sensor offset on a plant that the candidate models exactly otherwise, against a model
    in use that knows the offset but has its input gain 20 % off. Scored plainly the offset
    dominates and the candidate is refused; scored as the offset-free MPC plans (the 'state'
    disturbance: the one-step residual is constant, so the estimate converges to it at rate
    1 - g and the corrected prediction is exact), its error vanishes and it flies."""
    exact = predictor(theta=0.0)
    u, y = linear_data(exact, [0.3, -0.2])
    d = manual(theta=0.0)
    knows_offset = dict(d.params, B=1.2 * d.params['B'])
    in_use = NssmPredictor(d.config, d.norm, knows_offset)
    in_use.latent.d = in_use.latent.d + np.array([0.3, -0.2])
    cfg = ModelCheckConfig(model_check_window=150)      # the estimate starts 10 before
    plain = check(exact, in_use, u, y, MPC, cfg)    # offset_free state, not as planned
    assert not plain.ok and plain.candidate > plain.reference
    corrected = check(exact, in_use, u, y, MpcConfig(offset_free='state', disturbance_gain=0.5),
                      dataclasses.replace(cfg, model_check_as_planned=True))
    assert corrected.ok and 'offset-free state, as planned' in corrected.reason()
    # The estimate starts warmup(g) samples before the scored ones, (1 - g)^W <= 1e-3: the
    # squared error left is at most ~1e-6 of the uncorrected offset's.
    assert corrected.candidate < 1e-6 * plain.candidate
    assert corrected.reference > 0.05 * plain.reference     # the gain error stays
    assert [warmup(g) for g in (1.0, 0.5, 0.1)] == [1, 10, 66]


def test_a_candidate_whose_disturbance_is_not_detectable_is_refused_by_the_check():
    """The output disturbance with an eigenvalue of A at 1 (the rank condition fails): the
    offset-free MPC could not use the model, so the check refuses it with the rank."""
    d = manual(theta=0.0)
    a = d.params['A'].numpy().astype(np.float64)
    a[1, :], a[1, 1] = 0.0, 1.0          # the second latent state integrates: eigenvalue 1
    integrating = NssmPredictor(d.config, d.norm, dict(d.params, A=a))
    u, y = plant_data()
    verdict = check(integrating, predictor(), u, y, MpcConfig(offset_free='output'),
                    ModelCheckConfig(model_check_as_planned=True))
    assert not verdict.ok and 'not detectable' in verdict.reason() and 'eigenvalue at 1' in (
        verdict.reason())


def test_the_controller_scores_as_planned_when_asked():
    """model_check_as_planned: the core hands the check its MPC's offset-free form and gain."""
    for planned in (False, True):
        core = _ran_60_steps(GateConfig(model_check='all'),
                             ModelCheckConfig(model_check_as_planned=planned))
        reason = core.offer(build_model(manual(flip=True), 2, 'manual', 'adapted', MPC, 1,
                                        2)).reason
        assert reason.startswith('check: its 20-step prediction error') and (
            ('(offset-free state, as planned)' in reason) == planned), reason


def error_by_hand(model, u, y, horizon, scored, stride):
    """E of `model` (None: persistence) on the last `scored` samples of u, y, by the module's
    definition written out: starts t = K - scored - 1, ... (stride) with t + N < K, each
    output scaled by its std over the scored samples and the H before them."""
    k, h = len(y), model.config.history if model is not None else 1
    scale = np.std(y[k - scored - h:], axis=0)
    errors = []
    for t in range(k - scored - 1, k - horizon, stride):
        if model is None:
            pred = np.repeat(y[t:t + 1], horizon, axis=0)
        else:
            pred = model.predict(u[t - h + 1:t + 1], y[t - h + 1:t + 1],
                                 u[t + 1:t + 1 + horizon])
        errors.append((y[t + 1:t + 1 + horizon] - pred) / scale)
    return float(np.mean(np.square(errors)))


def test_the_errors_are_those_of_exactly_the_scored_samples():
    """Both errors equal the definition worked out by hand on the last 100 samples: a check
    that scored one sample more or fewer (its starts shifted by one) would not."""
    u, y = plant_data()
    good, bad = predictor(), predictor(flip=True)
    verdict = check(bad, good, u, y, MPC, ModelCheckConfig(), scored=100)
    assert verdict.candidate == pytest.approx(error_by_hand(bad, u, y, 20, 100, 5), rel=1e-9)
    assert verdict.reference == pytest.approx(error_by_hand(good, u, y, 20, 100, 5), rel=1e-9)
    assert 'on 100 samples' in verdict.reason() and verdict.scored == 100


def test_the_margin_lets_a_candidate_a_known_factor_worse_fly_just_above_that_factor():
    """The flipped model's error is F times the good one's (by hand): it flies at a margin
    just above F - 1 and is refused just below it."""
    u, y = plant_data()
    good, bad = predictor(), predictor(flip=True)
    factor = error_by_hand(bad, u, y, 20, 100, 5) / error_by_hand(good, u, y, 20, 100, 5)
    assert factor > 1.25
    above = check(bad, good, u, y, MPC, ModelCheckConfig(model_check_margin=factor - 1 + 1e-6),
                  scored=100)
    below = check(bad, good, u, y, MPC, ModelCheckConfig(model_check_margin=factor - 1 - 1e-6),
                  scored=100)
    assert above.ok and not below.ok
    assert f'exceeds {factor - 1e-6:g} x ' in below.reason()


def test_a_candidate_exactly_as_good_as_the_model_in_use_passes_at_margin_0():
    u, y = plant_data()
    verdict = check(predictor(), predictor(), u, y, MPC, ModelCheckConfig(), scored=100)
    assert verdict.candidate == verdict.reference and verdict.ok
