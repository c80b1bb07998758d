"""The model gate's rules (model_gate) against hand-worked cases, without ROS.

Every case: dt 0.1 s, periodic requests every 2 s, swap_delay 10: the tick of step 20 asks
(model 1 in use), and under lockstep its answer is used or tried from the tick of step 30. The
check is a stub that passes a model at the scored lengths it is made to pass (None: at
arrival), so each case's outcome is known by hand.
"""
import dataclasses
import math
from types import SimpleNamespace
from typing import NamedTuple, Optional

import numpy as np
import pytest

from metampc_controller.adaptation_trigger import AdaptationTrigger, TriggerConfig
from metampc_controller.controller_core import build_model, ControllerCore
from metampc_controller.controller_params import ControllerConfig
from metampc_controller import model_gate
from metampc_controller.model_check import ModelCheckConfig, Verdict
from metampc_controller.model_gate import GateConfig, ModelGate, Outcome
from metampc_controller.mpc import MpcConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.plant_description import PlantDescription

DT = 0.1
TRIGGER = TriggerConfig(adaptation='periodic', adapt_period=2.0, swap_delay=10)
ALWAYS = frozenset({None, 6, 11})      # arrival, a trial of 5, a probation of 10


class Mpc:
    """The planner of a stub model: counts its resets (a reverted model restarts cold)."""

    def __init__(self):
        self.resets = 0

    def reset(self):
        self.resets += 1


class Model(NamedTuple):
    """A model the stub check passes at the scored lengths in `passes`."""

    version: int
    passes: frozenset = ALWAYS
    method: str = 'imaml'
    latent: object = 'nssm'        # None: a feature NARX (the check is the NSSM's)
    mpc: Mpc = None

    @property
    def predictor(self):
        return self


def stub_check(candidate, current, u, y, mpc, config, scored=None):
    """The check's verdict as `candidate.passes` says, with errors 1 (passes) or 3 against
    2 and the samples scored (`scored`, or 200 at arrival)."""
    ok = scored in candidate.passes
    return Verdict(ok, 1.0 if ok else 3.0, 2.0, scored or 200, limit=1.0,
                   score='10-step prediction error')


@pytest.fixture
def stubbed(monkeypatch):
    """model_gate's check replaced by :func:`stub_check`."""
    monkeypatch.setattr(model_gate, 'check', stub_check)


def settings(check='requested', trial=0, probation=0):
    return SimpleNamespace(mpc=MpcConfig(), model_check=ModelCheckConfig(),
                           gate=GateConfig(check, trial, probation))


IN_USE = Model(1)
GOOD = Model(2)
BAD = Model(2, frozenset())
FAILS_PROBATION = Model(2, frozenset({None, 6}))
NARX = Model(2, frozenset(), latent=None)


def run(config, offers=None, lockstep=True, steps=range(15, 60), give_up_at=None):
    """Ticks over `steps` as the controller makes them, model 1 in use: before each tick the
    offers {step: (model, request_step)} and, at `give_up_at`, the request's timeout; after
    it the trigger's update. Returns [(step, outcome, version, cause)] of the gate's events
    and the requests made, ('request' rows), and the model in use at the end."""
    gate = ModelGate(AdaptationTrigger(TRIGGER), lambda: (np.zeros((0, 1)), np.zeros((0, 2))),
                     lockstep)
    in_use, log = Model(1, mpc=Mpc()), []

    def took(step, events):
        nonlocal in_use
        for e in events:
            log.append((step, e.outcome.value, e.version, e.cause.value))
            in_use = e.model or in_use
    for k in steps:
        if k == give_up_at:
            assert gate.time_out(gate.trigger.pending)
        if offers and k in offers:
            model, request_step = offers[k]
            took(k, [gate.offer(model._replace(mpc=Mpc()), request_step, in_use, config)])
        took(k, gate.tick(k, in_use, config))
        if gate.trigger.update(k, DT, math.nan, math.nan, in_use.version) is not None:
            log.append((k, 'request', in_use.version, ''))
    return log, in_use


# (case, settings, offers, lockstep, give_up_at, events and requests, version in use at the end)
RULES = [
    ('a model naming no request flies at arrival, unchecked under requested',
     settings(), {25: (BAD, 0)}, True, None,
     [(20, 'request', 1, ''), (25, 'flew', 2, 'unchecked')], 2),
    ('under all a model naming no request is checked at arrival: a worse one is refused',
     settings('all'), {25: (BAD, 0)}, True, None,
     [(20, 'request', 1, ''), (25, 'refused', 2, 'check')], 1),
    ('under all a better one flies at arrival with its verdict',
     settings('all'), {25: (GOOD, 0)}, True, None,
     [(20, 'request', 1, ''), (25, 'flew', 2, 'check')], 2),
    ('off: even a worse answer to the request flies at its swap step, unchecked',
     settings('off', trial=5), {25: (BAD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'flew', 2, 'unchecked'),
      (40, 'request', 2, '')], 2),
    ('no trial: a worse answer is refused at arrival and its request ends (asked again)',
     settings(), {25: (BAD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'refused', 2, 'check'), (40, 'request', 1, '')], 1),
    ('no trial: a better answer, checked at arrival, flies at request + swap_delay',
     settings(), {25: (GOOD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'check'), (30, 'flew', 2, 'unchecked'),
      (40, 'request', 2, '')], 2),
    ('a trial starts at the swap step, the model in use going on; a better answer flies at '
     'its end', settings(trial=5), {25: (GOOD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'on_trial', 2, 'unchecked'),
      (35, 'flew', 2, 'check'), (40, 'request', 2, '')], 2),
    ('a worse answer is refused at the end of its trial and its request ends',
     settings(trial=5), {25: (BAD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'on_trial', 2, 'unchecked'),
      (35, 'refused', 2, 'check'), (40, 'request', 1, '')], 1),
    ('probation: an answer that stays the better predictor is kept, its request pending until '
     'then', settings(trial=5, probation=10), {25: (GOOD, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'on_trial', 2, 'unchecked'),
      (35, 'flew', 2, 'check'), (45, 'kept', 2, 'check'), (45, 'request', 2, '')], 2),
    ('probation: an answer worse on its own loop is reverted to the model it replaced',
     settings(trial=5, probation=10), {25: (FAILS_PROBATION, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'on_trial', 2, 'unchecked'),
      (35, 'flew', 2, 'check'), (45, 'reverted', 2, 'check'), (45, 'request', 1, '')], 1),
    ('a late answer (its request given up) is not tried but checked at arrival',
     settings(trial=5), {25: (BAD, 20)}, True, 22,
     [(20, 'request', 1, ''), (25, 'refused', 2, 'check'), (40, 'request', 1, '')], 1),
    ('a feature NARX answer is never checked (the check is the NSSM\'s)',
     settings('all'), {25: (NARX, 20)}, True, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'unchecked'), (30, 'flew', 2, 'unchecked'),
      (40, 'request', 2, '')], 2),
    ('real time: the answer flies at the next tick, early or late',
     settings(), {25: (GOOD, 20)}, False, None,
     [(20, 'request', 1, ''), (25, 'queued', 2, 'check'), (25, 'flew', 2, 'unchecked'),
      (40, 'request', 2, '')], 2),
]


@pytest.mark.parametrize('case, config, offers, lockstep, give_up_at, events, version', RULES,
                         ids=[r[0] for r in RULES])
def test_each_rule_gives_its_events(stubbed, case, config, offers, lockstep, give_up_at, events,
                                    version):
    log, in_use = run(config, offers, lockstep, give_up_at=give_up_at)
    assert log == events
    assert in_use.version == version


def test_a_reverted_model_comes_back_cold_and_the_events_say_why(stubbed):
    """The revert's event flies the replaced model (reset once: its plan is stale), states
    the model status with the check's reason, and the flight before it said 'ok'."""
    gate = ModelGate(AdaptationTrigger(TRIGGER), lambda: (None, None), lockstep=True)
    config, in_use = settings(trial=5, probation=10), Model(1, mpc=Mpc())
    gate.trigger.update(20, DT, math.nan, math.nan, 1)
    events = [gate.offer(FAILS_PROBATION._replace(mpc=Mpc()), 20, in_use, config)]
    for k in range(21, 46):
        for e in gate.tick(k, in_use, config):
            events.append(e)
            in_use = e.model or in_use
    flew, reverted = events[-2:]
    assert (flew.outcome, flew.status) == (Outcome.FLEW, 'ok')
    assert reverted.model.version == 1 and reverted.model.mpc.resets == 1
    assert reverted.status == ('reverted: check: its 10-step prediction error 3 on 11 samples '
                               '(its probation from step 35, on its own loop) exceeds 1 x 2 '
                               'of the model it replaced')
    assert [e.status for e in events[:2]] == [None, None]     # queued, on trial


def test_weights_that_could_not_be_built_are_refused_and_the_request_goes_on(stubbed):
    gate = ModelGate(AdaptationTrigger(TRIGGER), lambda: (None, None), lockstep=True)
    request = gate.trigger.update(20, DT, math.nan, math.nan, 1)
    event = gate.refuse(2, 20, 'non-finite weights')
    assert (event.outcome, event.cause.value, event.status) == (
        Outcome.REFUSED, 'weights', 'rejected: non-finite weights')
    assert gate.trigger.pending is request and event.model is None


def asked(lockstep: bool, trial=0, probation=0):
    """A gate whose trigger asked at step 20 (model 1 in use), and its settings."""
    gate = ModelGate(AdaptationTrigger(TRIGGER), lambda: (None, None), lockstep)
    request = gate.trigger.update(20, DT, math.nan, math.nan, 1)
    assert (request.step, request.swap_step) == (20, 30)
    return gate, settings(trial=trial, probation=probation)


def test_under_lockstep_the_tick_of_the_swap_step_waits_for_the_answer(stubbed):
    gate, config = asked(lockstep=True)
    assert [gate.waits(k) for k in (21, 29, 30)] == [False, False, True]
    assert gate.tick(30, IN_USE, config) == [] and gate.waits(30)   # still nothing
    assert gate.offer(GOOD, 20, IN_USE, config).start == 30     # arrives while 30 waits
    assert not gate.waits(30) and gate.tick(30, IN_USE, config)[0].model == GOOD


def test_a_given_up_request_no_longer_holds_the_swap_step(stubbed):
    gate, config = asked(lockstep=True)
    assert gate.learner_refused(19) is None and gate.waits(30)     # another request
    assert gate.learner_refused(20).step == 20
    assert not gate.waits(30) and gate.offer(GOOD, 20, IN_USE, config).outcome is Outcome.FLEW


def test_a_timeout_gives_up_only_a_request_with_no_answer_held(stubbed):
    gate, config = asked(lockstep=True, trial=5)
    request = gate.trigger.pending
    gate.offer(GOOD, 20, IN_USE, config)
    assert not gate.time_out(request) and gate.trigger.pending is request   # queued
    gate.new_episode()
    gate.trigger.new_episode()
    assert not gate.time_out(request)          # forgotten by the reset: not pending


def test_a_new_episode_forgets_the_held_answer(stubbed):
    for trial, probation in ((0, 0), (5, 0), (0, 5)):
        gate, config = asked(lockstep=True, trial=trial, probation=probation)
        gate.offer(GOOD, 20, IN_USE, config)
        if trial or probation:
            gate.tick(30, IN_USE, config)      # tried, or flown on probation
        assert gate.has_answer()
        gate.trigger.new_episode()
        gate.new_episode()
        assert not gate.has_answer() and [gate.tick(k, IN_USE, config) for k in range(30, 40)
                                          ] == [[]] * 10


def test_a_retune_rebuilds_the_held_answer_and_the_model_a_flown_one_replaced(stubbed):
    rebuilt = lambda m: m._replace(version=m.version + 10)     # noqa: E731
    gate, config = asked(lockstep=True)
    gate.retune(rebuilt)                       # nothing held: nothing to rebuild
    gate.offer(GOOD, 20, IN_USE, config)
    gate.retune(rebuilt)
    assert gate.tick(30, IN_USE, config)[0].model.version == 12
    gate, config = asked(lockstep=True, trial=5)
    gate.offer(GOOD, 20, IN_USE, config)
    gate.tick(30, IN_USE, config)
    gate.retune(rebuilt)
    assert gate.tick(35, IN_USE, config)[0].model.version == 12
    gate, config = asked(lockstep=True, probation=10)
    gate.offer(FAILS_PROBATION, 20, IN_USE._replace(mpc=Mpc()), config)
    gate.tick(30, IN_USE._replace(mpc=Mpc()), config)
    gate.retune(rebuilt)
    assert gate.tick(40, FAILS_PROBATION, config)[0].model.version == 11


def manual_bundle(version: int):
    return build_model(DecodedWeights(*linearised_vdp_nssm(0.5, DT, 10)), version, 'manual',
                       'adapted', MpcConfig(time_limit=30.0), 1, 2)


def test_a_live_change_between_queue_and_swap_step_applies_to_the_answer():
    """A change of the horizon (20 -> 10) accepted while the answer waits for its swap step:
    the tick of step 30 uses the answer with the new horizon; before, the answer kept the QP
    of the old one and that tick raised (y_ref of 10 rows for a QP of 20)."""
    config = ControllerConfig(trigger=TRIGGER, gate=GateConfig(model_check_trial=0))
    core = ControllerCore(config)
    core.set_plant(PlantDescription('vanderpol', DT, (-1.0,), (1.0,), 2, True))
    core.offer(manual_bundle(1))
    shorter = dataclasses.replace(config, mpc=MpcConfig(time_limit=30.0, horizon=10))
    for k in range(32):
        core.observe(k, [0.0], [0.3, 0.0])
        if k == 25:
            assert core.offer(manual_bundle(2), 20).start == 30
            core.retune(shorter, 1)
        res = core.tick()
        assert res.model_version == (2 if k >= 30 else 1)
        assert res.u_plan.shape == ((10 if k >= 25 else 20), 1) and res.config_version == (
            k >= 25)


def test_the_core_publishes_each_event_once_with_the_next_answer():
    """Events decided at arrival (between ticks) come with the next tick's answer, those of
    a tick with its own, each once: the model status follows them."""
    core = ControllerCore(ControllerConfig(gate=GateConfig(model_check='off')))
    core.observe(0, [0.0], [0.0, 0.0])
    assert core.tick().events == ()
    first = core.offer(manual_bundle(1))
    second = core.refuse(2, 0, 'non-finite weights')
    res = core.tick()
    assert res.events == (first, second) and res.model_version == 1
    assert res.model_status == 'rejected: non-finite weights'
    core.observe(1, [0.0], [0.0, 0.0])
    assert core.tick().events == ()


def gate_in_use(in_use: Optional[Model]):
    gate, config = asked(lockstep=True, trial=5)
    return gate.tried(20, in_use, config)


def test_no_trial_without_a_model_in_use_to_go_on_meanwhile(stubbed):
    assert (gate_in_use(IN_USE), gate_in_use(None)) == (5, 0)


def test_which_models_are_checked():
    requested, all_, off = (GateConfig(model_check=m) for m in ('requested', 'all', 'off'))
    assert [c.checks(True) for c in (requested, all_, off)] == [True, True, False]
    assert [c.checks(False) for c in (requested, all_, off)] == [False, True, False]


def test_an_answer_whose_request_ends_while_it_is_offered_is_checked_like_a_late_one(stubbed):
    """The request given up (its timeout, on the executor thread) after the gate found the
    answer to be tried but before it queued it: no trial to judge it, so it is checked at
    arrival like a late answer: a worse one refused, a better one flown with its verdict."""
    for model, outcome in ((BAD, Outcome.REFUSED), (GOOD, Outcome.FLEW)):
        gate, config = asked(lockstep=True, trial=5)
        queue = gate._queue

        def timed_out_first(*args):
            gate.trigger.give_up()
            return queue(*args)
        gate._queue = timed_out_first
        event = gate.offer(model, 20, IN_USE, config)
        assert (event.outcome, event.cause.value) == (outcome, 'check')
        assert event.verdict.scored == 200 and gate.trigger.pending is None
