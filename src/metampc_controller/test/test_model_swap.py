"""The swap rules (model_swap) against hand-worked cases, without ROS.

Every case: dt 0.1 s, periodic requests every 2 s, swap_delay 10: the tick of step 20 asks,
and under lockstep its answer is used from the tick of step 30 exactly.
"""
import dataclasses
import math
from typing import NamedTuple

from metampc_controller.adaptation_trigger import AdaptationTrigger, TriggerConfig
from metampc_controller.controller_core import build_model, ControllerCore
from metampc_controller.controller_params import ControllerConfig
from metampc_controller.model_check import ModelCheckConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_controller.model_swap import ModelSwap
from metampc_controller.mpc import MpcConfig
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.plant_description import PlantDescription

DT = 0.1
TRIGGER = TriggerConfig(adaptation='periodic', adapt_period=2.0, swap_delay=10)


class Model(NamedTuple):
    version: int


def asked(lockstep: bool) -> ModelSwap:
    """Rules whose trigger asked at step 20 (model 1 in use)."""
    swap = ModelSwap(AdaptationTrigger(TRIGGER), lockstep)
    request = swap.trigger.update(20, DT, math.nan, math.nan, 1)
    assert (request.step, request.swap_step) == (20, 30)
    return swap


def run(swap: ModelSwap, steps, offers=None):
    """Ticks over `steps` as the core makes them: {step: (waits, model used from it)}; offers
    {step: (model, request_step)} are offered before that step's tick (None: it waits)."""
    out = {}
    for k in steps:
        if offers and k in offers:
            swap.offer(*offers[k])
        used = swap.due(k)
        out[k] = (swap.waits(k), used.version if used is not None else None)
    return out


def test_under_lockstep_an_early_answer_is_used_at_request_plus_swap_delay():
    swap = asked(lockstep=True)
    assert swap.offer(Model(2), 20) == 30           # offered at step 25: queued for 30
    ticks = run(swap, range(25, 35))
    assert [k for k, (_, used) in ticks.items() if used] == [30]
    assert ticks[30] == (False, 2) and not any(w for w, _ in ticks.values())
    assert swap.trigger.pending is None             # answered


def test_under_lockstep_the_tick_of_the_swap_step_waits_for_the_answer():
    swap = asked(lockstep=True)
    assert [swap.waits(k) for k in (21, 29, 30)] == [False, False, True]
    assert swap.due(30) is None and swap.waits(30)  # still nothing: still waits
    assert swap.offer(Model(2), 20) == 30           # arrives while the tick of 30 waits
    assert not swap.waits(30) and swap.due(30) == Model(2)


def test_in_real_time_an_answer_is_used_at_the_next_tick_early_or_late():
    early = asked(lockstep=False)
    assert early.offer(Model(2), 20) == 0           # before the swap step: the next tick
    assert run(early, [24, 25]) == {24: (False, 2), 25: (False, None)}
    late = asked(lockstep=False)
    ticks = run(late, range(21, 40), offers={37: (Model(3), 20)})
    assert not any(w for w, _ in ticks.values())    # nothing waits in real time
    assert [k for k, (_, used) in ticks.items() if used] == [37]


def test_a_model_that_answers_no_pending_request_is_the_callers_to_use_at_once():
    swap = asked(lockstep=True)
    for request_step in (0, 19, 21):                # none, or another request
        assert swap.offer(Model(5), request_step) is None
    assert swap.trigger.pending.step == 20 and swap.waits(30)   # the request still waits
    plain = ModelSwap(AdaptationTrigger(TRIGGER), lockstep=True)
    assert plain.offer(Model(2), 20) is None        # no request pending at all


def test_a_refused_answer_ends_the_request_and_the_model_in_use_stays():
    swap = asked(lockstep=True)
    swap.refused(0)                                  # a refused model of no request: nothing
    swap.refused(19)
    assert swap.trigger.pending is not None and swap.waits(30)
    swap.refused(20)                                 # the answer refused
    assert swap.trigger.pending is None
    assert run(swap, range(28, 33)) == {k: (False, None) for k in range(28, 33)}
    assert swap.offer(Model(2), 20) is None          # a second answer: no request any more


def test_a_given_up_request_no_longer_holds_the_swap_step():
    swap = asked(lockstep=True)
    swap.trigger.give_up()                           # adapt_timeout
    assert not swap.waits(30) and swap.offer(Model(2), 20) is None


def test_a_new_episode_forgets_the_queued_answer():
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20)
    swap.trigger.new_episode()
    swap.new_episode()
    assert run(swap, [30, 31]) == {30: (False, None), 31: (False, None)}


def test_a_retune_rebuilds_the_queued_answer():
    swap = asked(lockstep=True)
    swap.retune(lambda m: Model(99))                 # nothing queued: nothing to rebuild
    swap.offer(Model(2), 20)
    swap.retune(lambda m: Model(m.version + 10))
    assert swap.due(30) == Model(12)


def test_an_answer_with_a_trial_is_tried_from_its_swap_step_then_judged():
    """Trial of 5 samples: the tick of 30 starts it (the model in use goes on, nothing
    waits), the tick of 35 ends it; a pass answers the request, a refusal ends it."""
    for ok in (True, False):
        swap = asked(lockstep=True)
        assert swap.offer(Model(2), 20, trial=5) == 30
        ticks = run(swap, range(25, 40))
        assert not any(w or used for w, used in ticks.values())
        assert swap.trigger.pending is not None         # not answered while tried
        assert [swap.trial_over(k) for k in (33, 34)] == [None, None]
        assert swap.trial_over(35) == (30, Model(2)) and swap.trial_over(36) is None
        swap.judged(35, Model(2), ok, Model(1))
        assert swap.trigger.pending is None and not swap.holds_answer()
        assert swap.trigger._version == (2 if ok else 1)     # whose baseline is measured


def test_a_flown_answer_on_probation_keeps_its_request_until_the_verdict():
    """Probation of 5 samples, no trial: the answer flies at the tick of 30, the request stays
    pending (no new one, nothing waits) until the tick of 35 ends the probation with (30, the
    answer, the model it replaced); kept answers the request for it, a revert ends it with
    the replaced model's baseline."""
    for ok in (True, False):
        swap = asked(lockstep=True)
        assert swap.offer(Model(2), 20, probation=5) == 30
        assert swap.due(30, Model(1)) == Model(2)
        assert swap.trigger.pending is not None and swap.holds_answer()
        assert not any(swap.waits(k) for k in range(30, 36))
        assert swap.trigger.update(34, DT, math.nan, math.nan, 2) is None   # no new request
        assert [swap.probation_over(k) for k in (33, 34)] == [None, None]
        assert swap.probation_over(35) == (30, Model(2), Model(1))
        assert swap.probation_over(36) is None and not swap.holds_answer()
        swap.kept(Model(2), ok)
        assert swap.trigger.pending is None
        assert swap.trigger._version == (2 if ok else 1)


def test_probation_follows_a_passed_trial_and_is_skipped_without_a_replaced_model():
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20, trial=5, probation=20)
    run(swap, range(28, 36))
    swap.trial_over(35)
    swap.judged(35, Model(2), True, Model(1))        # flies at 35, on probation until 55
    assert swap.trigger.pending is not None
    assert swap.probation_over(54) is None
    assert swap.probation_over(55) == (35, Model(2), Model(1))
    swap.retune(lambda m: Model(m.version + 10))     # nothing held any more
    first = asked(lockstep=True)                     # no model in use before: nothing to judge
    first.offer(Model(2), 20, probation=5)
    assert first.due(30, None) == Model(2) and first.trigger.pending is None


def test_a_retune_rebuilds_the_replaced_model_and_a_new_episode_forgets_the_probation():
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20, probation=5)
    swap.due(30, Model(1))
    swap.retune(lambda m: Model(m.version + 10))
    assert swap.probation_over(35) == (30, Model(2), Model(11))
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20, probation=5)
    swap.due(30, Model(1))
    swap.trigger.new_episode()
    swap.new_episode()
    assert swap.probation_over(35) is None and not swap.holds_answer()


def test_in_real_time_a_trial_starts_at_the_next_tick():
    swap = asked(lockstep=False)
    run(swap, range(21, 40), offers={37: (Model(3), 20, 4)})
    assert swap.trial_over(40) is None and swap.trial_over(41) == (37, Model(3))


def test_a_new_episode_forgets_the_tried_answer_and_a_retune_rebuilds_it():
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20, trial=5)
    swap.due(30)
    swap.retune(lambda m: Model(m.version + 10))
    assert swap.trial_over(35) == (30, Model(12))
    swap = asked(lockstep=True)
    swap.offer(Model(2), 20, trial=5)
    swap.due(30)
    swap.trigger.new_episode()
    swap.new_episode()
    assert swap.trial_over(35) is None and not swap.waits(30)


def test_a_live_change_between_queue_and_swap_step_applies_to_the_answer():
    """A change of the horizon (20 -> 10) accepted while the answer waits for its swap step:
    the tick of step 30 uses the answer with the new horizon; before, the answer kept the QP
    of the old one and that tick raised (y_ref of 10 rows for a QP of 20)."""
    bundle = build_model(DecodedWeights(*linearised_vdp_nssm(0.5, DT, 10)), 1, 'manual',
                         'adapted', MpcConfig(time_limit=30.0), 1, 2)
    config = ControllerConfig(trigger=TRIGGER, model_check=ModelCheckConfig(model_check_trial=0))
    core = ControllerCore(config)
    core.set_plant(PlantDescription('vanderpol', DT, (-1.0,), (1.0,), 2, True))
    core.offer_model(bundle)
    shorter = dataclasses.replace(config, mpc=MpcConfig(time_limit=30.0, horizon=10))
    for k in range(32):
        core.observe(k, [0.0], [0.3, 0.0])
        if k == 25:
            assert core.offer_model(dataclasses.replace(bundle, version=2), 20) == 30
            core.retune(shorter, 1)
        res = core.tick()
        assert res.model_version == (2 if k >= 30 else 1)
        assert res.u_plan.shape == ((10 if k >= 25 else 20), 1) and res.config_version == (
            k >= 25)
