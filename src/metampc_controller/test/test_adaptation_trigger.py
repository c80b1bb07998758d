"""AdaptationTrigger: the periodic and CUSUM request rules, their hysteresis, and the queued
swap of a requested model in the controller core (lockstep: exactly at the swap step)."""
import dataclasses
import math

import numpy as np
import pytest

from metampc_controller.adaptation_trigger import AdaptationTrigger, TriggerConfig
from metampc_controller.controller_core import build_model, ControllerCore
from metampc_controller.controller_params import ControllerConfig
from metampc_controller.model_gate import GateConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_controller.mpc import MpcConfig
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.plant_description import PlantDescription
from metampc_plant.simulator import Plant, PlantConfig

DT = 0.1


def feed(trigger, errors, start=0, version=1, change=None):
    """Feed errors from step `start` (with the outputs' change that makes the relative error
    e / (change + floor) equal e: change = 1 - floor); the steps of the requests made."""
    change = 1.0 - trigger.config.error_floor if change is None else change
    out = []
    for i, e in enumerate(errors):
        request = trigger.update(start + i, DT, e, change, version)
        if request is not None:
            out.append(request.step)
    return out


def test_periodic_requests_at_each_period_one_at_a_time():
    trigger = AdaptationTrigger(TriggerConfig(adaptation='periodic', adapt_period=2.0))
    assert feed(trigger, [1.0] * 25) == [20]        # t = 2.0 s; then pending: nothing more
    assert trigger.pending.swap_step == 30 and trigger.waits(30) and not trigger.waits(29)
    trigger.answered(2)
    assert feed(trigger, [1.0] * 30, start=25, version=2) == [40]   # t = 4.0 s
    trigger.give_up()
    assert feed(trigger, [1.0] * 30, start=55, version=2) == [60]  # t = 6.0, then pending


def test_cusum_requests_after_the_analytic_number_of_steps():
    """Baseline 1 (median of the first 3 s = 30 samples); errors x10 from step 50: s grows by
    log 10 - 1 = 1.303 per step and passes 5 at the 4th such step (5.21): step 53."""
    cfg = TriggerConfig(adaptation='triggered', cusum_drift=1.0, cusum_threshold=5.0,
                        baseline_s=3.0)
    trigger = AdaptationTrigger(cfg)
    rng = np.random.default_rng(0)
    noise = np.exp(0.3 * rng.standard_normal(50))      # around the baseline: never accumulates
    errors = [math.nan] * 5 + list(noise[5:]) + [10.0] * 10
    assert feed(trigger, errors) == [53]
    assert trigger.baseline == pytest.approx(np.median(noise[5:35]))
    assert trigger.statistic > cfg.cusum_threshold


def test_no_request_while_the_baseline_is_measured_nor_while_one_is_pending():
    trigger = AdaptationTrigger(TriggerConfig(adaptation='triggered', baseline_s=3.0,
                                              cusum_drift=1.0, cusum_threshold=5.0))
    # log 100 - 1 = 3.6 per step: past 5 at the second step of the jump.
    assert feed(trigger, [1.0] * 30 + [100.0] * 4) == [31]
    assert feed(trigger, [100.0] * 50, start=34) == []      # pending: one at a time
    trigger.answered(2)     # the new model's baseline is measured first: 3 s of any errors
    assert feed(trigger, [100.0] * 30, start=84, version=2) == []
    assert trigger.baseline == 100.0
    assert feed(trigger, [100.0] * 100, start=114, version=2) == []  # its own level: no request


def test_the_error_is_relative_to_the_outputs_motion():
    """Errors 100 times larger while the outputs move 100 times more (a set-point step) ask
    nothing; the same errors at rest do."""
    trigger = AdaptationTrigger(TriggerConfig(adaptation='triggered', error_floor=0.01,
                                              baseline_s=3.0, cusum_drift=1.0,
                                              cusum_threshold=5.0))
    feed(trigger, [0.01] * 30, change=0.0)      # at rest: relative error 1
    assert trigger.baseline == pytest.approx(1.0)
    assert feed(trigger, [1.0] * 20, start=30, change=0.99) == []  # moving: still 1
    assert feed(trigger, [1.0] * 5, start=50, change=0.0) == [51]  # at rest: 100


def test_a_new_model_or_episode_restarts_the_baseline_and_off_asks_nothing():
    trigger = AdaptationTrigger(TriggerConfig(adaptation='triggered', baseline_s=3.0))
    feed(trigger, [1.0] * 40)
    assert trigger.baseline == 1.0
    feed(trigger, [1.0], start=40, version=7)   # a model swapped in by someone else
    assert math.isnan(trigger.baseline)
    feed(trigger, [1.0] * 40, start=41, version=7)
    trigger.new_episode()
    assert math.isnan(trigger.baseline) and trigger.pending is None
    off = AdaptationTrigger(TriggerConfig())
    assert feed(off, [1.0] * 30 + [1e6] * 50) == []


def test_posterior_requests_when_the_chi_square_window_rejects_and_starts_again_after():
    """W 5, alpha 1e-3, 2 outputs: threshold chi2.isf(1e-3, 10) = 29.59 (tables). Unit
    innovations sum to 10 per window: no request; innovations of 2.5 per output (12.5 per
    tick) after 10 unit ticks: the sum is 2 (5 - j) + 12.5 j, above 29.59 at j = 2 (31). None
    (no RLS) asks nothing; the model answering the request starts an empty window. Fails on
    a posterior rule that reads the T-step error or keeps the window across models."""
    cfg = TriggerConfig(adaptation='posterior', posterior_window=5, posterior_alpha=1e-3)
    trigger = AdaptationTrigger(cfg)
    for k in range(20):
        assert trigger.update(k, DT, 1e6, 0.0, 1, None) is None
    steps = []
    for k, nu in enumerate([1.0] * 10 + [2.5] * 3):
        request = trigger.update(20 + k, DT, 1e6, 0.0, 1, np.full(2, nu))
        if request is not None:
            steps.append((request.step, request.trigger))
    assert steps == [(31, 'posterior')]
    assert trigger.baseline == pytest.approx(29.588, abs=1e-3)
    assert trigger.statistic == pytest.approx(3 * 2 + 2 * 12.5)
    trigger.answered(2)
    assert trigger.update(40, DT, 1.0, 1.0, 2, np.full(2, 10.0)) is None   # 1 of 5 ticks
    assert trigger.statistic == pytest.approx(200.0)


def test_bad_settings_are_refused():
    for bad in (dict(adapt_period=0.0), dict(cusum_threshold=-1.0), dict(swap_delay=0),
                dict(adaptation='sometimes'), dict(posterior_window=0),
                dict(posterior_alpha=1.0)):
        with pytest.raises(ValueError):
            TriggerConfig(**bad).validate()


def test_the_core_swaps_a_requested_model_exactly_at_the_swap_step_under_lockstep():
    """A periodic request at t = 2 s (step 20): the answer of step 30 waits for the model; a
    model offered early (at step 25) is used from step 30 on, not before; ticks after it use
    it and the trigger counts it answered."""
    bundle = build_model(DecodedWeights(*linearised_vdp_nssm(0.5, DT, 10)), 1, 'manual',
                         'adapted', MpcConfig(time_limit=30.0), 1, 2)
    config = ControllerConfig(trigger=TriggerConfig(adaptation='periodic', adapt_period=2.0),
                              gate=GateConfig(model_check_trial=0))
    core = ControllerCore(config)
    core.set_plant(PlantDescription('vanderpol', DT, (-1.0,), (1.0,), 2, True))
    core.offer(bundle)
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, 0.0)))
    y, u, versions, requests = plant.output(), 0.0, [], []
    for k in range(40):
        core.observe(k, [u], y)
        if k == 25:
            assert core.offer(dataclasses.replace(bundle, version=2), 20).start == 30
        assert core.waits_for_model() is False
        res = core.tick()
        versions.append(res.model_version)
        if res.request is not None:
            requests.append((k, res.request.swap_step))
        u = float(res.u[0])
        y = plant.step([u])
    assert requests == [(20, 30)]     # the next period (t = 4 s) is step 40
    assert versions[:30] == [1] * 30 and versions[30:] == [2] * 10
    # Without the model, the answer of the swap step waits (and not before).
    core2 = ControllerCore(config)
    core2.set_plant(PlantDescription('vanderpol', DT, (-1.0,), (1.0,), 2, True))
    core2.offer(bundle)
    for k in range(31):
        core2.observe(k, [0.0], [0.3, 0.0])
        assert core2.waits_for_model() == (k == 30)
        if k < 30:
            core2.tick()


def test_a_given_up_request_measures_the_baseline_again_before_asking_again():
    """Pins give_up (the node's adapt_timeout; docstring: keep the model in use, ask again
    later): the request is dropped and the model in use gets a fresh baseline and statistic,
    so the errors that caused the request ask nothing while they are measured (3 s) and become
    the new baseline (100); only errors 100 times that ask again, at the analytic step: log 100
    - 1 = 3.6 per step, past 5 at the second."""
    trigger = AdaptationTrigger(TriggerConfig(adaptation='triggered', baseline_s=3.0,
                                              cusum_drift=1.0, cusum_threshold=5.0))
    assert feed(trigger, [1.0] * 30 + [100.0] * 4) == [31]
    trigger.give_up()
    assert trigger.pending is None and not trigger.waits(41)
    assert trigger.statistic == 0.0 and math.isnan(trigger.baseline)
    assert feed(trigger, [100.0] * 30, start=34) == []      # the baseline, measured anew
    assert trigger.baseline == 100.0
    assert feed(trigger, [100.0] * 20, start=64) == []      # at its own level: nothing
    assert feed(trigger, [1e4] * 3, start=84) == [85]       # asked again, model 1 kept
    assert trigger.pending.version == 1


def test_the_statistic_at_the_threshold_asks_nothing():
    """Pins the threshold at equality against the documented rule (docs/adaptation.md and the
    module: a request when s_k > cusum_threshold, strictly): baseline 1, drift 1, threshold
    log 8 - 1 computed as the CUSUM adds it; an error of 8 brings s to the threshold exactly,
    no request; the next one (s = 2 (log 8 - 1)) asks. A hair above 8 asks at once."""
    threshold = 0.0 + math.log(8.0 / 1.0) - 1.0
    cfg = TriggerConfig(adaptation='triggered', baseline_s=3.0, cusum_drift=1.0,
                        cusum_threshold=threshold)
    trigger = AdaptationTrigger(cfg)
    assert feed(trigger, [1.0] * 30) == [] and trigger.baseline == 1.0
    assert feed(trigger, [8.0], start=30) == []
    assert trigger.statistic == cfg.cusum_threshold and trigger.pending is None
    assert feed(trigger, [8.0], start=31) == [31]
    above = AdaptationTrigger(cfg)
    assert feed(above, [1.0] * 30 + [8.0 * (1 + 1e-12)]) == [30]


def _lockstep_core(trigger: TriggerConfig):
    bundle = build_model(DecodedWeights(*linearised_vdp_nssm(0.5, DT, 10)), 1, 'manual',
                         'adapted', MpcConfig(time_limit=30.0), 1, 2)
    core = ControllerCore(ControllerConfig(trigger=trigger))
    core.set_plant(PlantDescription('vanderpol', DT, (-1.0,), (1.0,), 2, True))
    core.offer(bundle)
    return core, bundle


def test_the_core_goes_on_after_a_given_up_request_and_forgets_one_at_a_plant_reset():
    """Pins the trigger through ControllerCore (lockstep, periodic every 2 s): a request given
    up (as the node's adapt_timeout does) no longer holds its swap step's answer, the model in
    use stays, and the next period asks; a plant reset (step 0 again) forgets the pending
    request and its queued answer (never swapped in; the new request's swap step waits) and
    restarts the periods at the new episode's t = 0 (a request at its step 20, not 40)."""
    core, bundle = _lockstep_core(TriggerConfig(adaptation='periodic', adapt_period=2.0))
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, 0.0)))
    y, u, log = plant.output(), 0.0, []

    def run(steps, first=0, before=None):
        nonlocal y, u
        for k in range(first, first + steps):
            core.observe(k, [u], y)
            if before is not None:
                before(k)
            waits = core.waits_for_model()
            res = core.tick()
            log.append((k, waits, res.model_version,
                        None if res.request is None else res.request.swap_step))
            u = float(res.u[0])
            y = plant.step([u])

    def give_up(k):
        if k == 25:
            core.trigger.give_up()

    run(45, before=give_up)
    assert [(k, s) for k, _, _, s in log if s is not None] == [(20, 30), (40, 50)]
    assert not any(w for _, w, _, _ in log) and {v for _, _, v, _ in log} == {1}
    assert core.offer(dataclasses.replace(bundle, version=2), 40).start == 50   # queued
    log.clear()
    y, u = plant.reset(), 0.0
    run(31)
    assert core.trigger.pending is not None and core.trigger.pending.step == 20
    assert [(k, s) for k, _, _, s in log if s is not None] == [(20, 30)]
    assert [k for k, w, _, _ in log if w] == [30]   # the new request's, not the old one's
    assert {v for _, _, v, _ in log} == {1}     # the forgotten answer never came into use


def test_the_core_forgets_the_baseline_at_a_plant_reset():
    """Pins new_episode through ControllerCore.observe (module docstring: a reset forgets the
    baseline, the statistic and the request): a triggered core with a measured baseline (0.5
    s) has none after step 0 comes again, and measures it anew over the new episode."""
    core, _ = _lockstep_core(TriggerConfig(adaptation='triggered', baseline_s=0.5))
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, 0.0)))
    y, u = plant.output(), 0.0
    for k in range(30):
        core.observe(k, [u], y)
        u = float(core.tick().u[0])
        y = plant.step([u])
    assert math.isfinite(core.trigger.baseline)
    core.trigger.statistic = 3.0
    assert core.observe(0, [0.0], plant.reset()) is True
    assert math.isnan(core.trigger.baseline) and core.trigger.statistic == 0.0
