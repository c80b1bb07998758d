"""The controller's tick without ROS: history, answer rule, pre-model input, model checks, and
closed loops of ControllerCore on the plant core, checked against independent answers."""
from collections import Counter
import dataclasses
import math

import numpy as np
import pytest

from metampc_controller.controller_core import (AnswerRule, build_model, ControllerCore,
                                                History, PreModelInput)
from metampc_controller.closed_loop import run_episode
from metampc_controller.controller_params import ControllerConfig
from metampc_common.excitation import ExcitationConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_controller.mpc import MpcConfig
from metampc_controller.nmpc import Nmpc
from metampc_model.weights_codec import DecodedWeights, WeightsError
from metampc_plant.plant_description import PlantDescription
from metampc_plant.simulator import Plant, PlantConfig


# OSQP's wall-clock cap (MpcConfig.time_limit, 50 ms) trips when a loaded machine stalls the
# process and turns the solve into a fallback: the closed loops below set it out of reach, as
# test_mpc.py does, since they check what the solver answers, not how fast.
NO_TIME_LIMIT = 30.0


def manual_bundle(version=1, theta=0.5, history=10, mpc=MpcConfig(time_limit=NO_TIME_LIMIT),
                  **model):
    return build_model(DecodedWeights(*linearised_vdp_nssm(theta, 0.1, history, **model)),
                       version, 'manual', 'adapted', mpc, 1, 2)


def test_history_window_pads_each_episode_with_its_first_sample():
    hist = History(capacity=4, n_u=1, n_y=2)
    samples = {k: ([0.1 * k], [k, -k]) for k in range(10)}
    for k in range(10):
        assert hist.append(k, *samples[k]) == (k == 0)
        u, y = hist.window(3)
        # The newest three, oldest first; before the third sample the first one repeats.
        expected = [max(j, 0) for j in range(k - 2, k + 1)]
        assert u.tolist() == [samples[j][0] for j in expected]
        assert y.tolist() == [samples[j][1] for j in expected]
        assert (hist.u.tolist(), hist.y.tolist(), hist.step) == (*samples[k], k)
    # Step 0 again (a plant reset), a jump (missed samples): new episodes, padded anew.
    for step in (0, 5):
        assert hist.append(step, [9.0], [9.0, 9.0])
        assert hist.window(4)[1].tolist() == [[9.0, 9.0]] * 4 and hist.length == 1
    with pytest.raises(ValueError):
        hist.window(5)


@pytest.mark.parametrize('lockstep', [False, True])
@pytest.mark.parametrize('seed', range(5))
def test_answer_rule_answers_every_lockstep_sample_once(seed, lockstep):
    """The plant publishes y_k only after the answer to y_{k-1}; the controller sees y_k and
    the timer tick of time k (/clock, another topic) in either order, and set_active may flip
    anywhere. Every sample must be answered exactly once, by the end of its events or at
    activation, never before it arrived; told that the plant is lockstep, the rule answers
    every sample that arrives while active on its arrival."""
    rng = np.random.default_rng(seed)
    rule = AnswerRule(active=True, lockstep=lockstep)
    answers = Counter()
    arrived = -1

    def answer():
        assert not rule.answered(arrived)       # unbounded: never inactive by itself
        answers[arrived] += 1

    for k in range(300):
        events = ['sample', 'tick'] if k > 0 else ['sample']   # the first tick is at dt
        rng.shuffle(events)
        if rng.random() < 0.2:
            off = int(rng.integers(0, len(events) + 1))
            on = int(rng.integers(off, len(events) + 1))
            events = events[:off] + ['off'] + events[off:on] + ['on'] + events[on:]
        for event in events:
            if event == 'sample':
                arrived = k
                active = rule.active
                if rule.on_sample():
                    answer()
                else:
                    assert not (lockstep and active), (seed, k, events)
            elif event == 'tick':
                if rule.on_tick():
                    answer()
            elif event == 'off':
                assert not rule.set_active(False)
            elif rule.set_active(True):
                answer()
        assert answers[k] == 1, (seed, k, events)
    assert set(answers.values()) == {1}


def test_answer_rule_inactive_from_start_answers_on_activation():
    rule = AnswerRule(active=False)
    assert not rule.on_sample() and not rule.on_tick()
    assert rule.set_active(True)            # y_0 waited: answered at activation
    rule.answered(0)
    assert not rule.set_active(True)        # already active: nothing to do
    assert not rule.on_tick()               # no new sample: the tick waits for one
    assert rule.on_sample()


def test_a_bounded_activation_ends_by_itself_exactly_there():
    """until_step: answers 0..n and goes inactive after answering n, so a lockstep plant
    stops at y_{n+1}; stop_at_escape: the first diverged sample stays unanswered."""
    rule = AnswerRule(active=False, lockstep=True)
    assert not rule.on_sample()                      # y_0 waits
    assert rule.set_active(True, until_step=2)       # answered at activation
    assert not rule.answered(0)
    assert rule.on_sample() and not rule.answered(1)
    assert rule.on_sample() and rule.answered(2)     # the bound: inactive by itself
    assert not rule.active and not rule.on_sample()  # y_3 waits
    # Stop at an escape, on y_5: y_3 and y_4 answered, y_5 not; deactivated bounds clear.
    assert rule.set_active(True, stop_at_escape=True) and not rule.answered(3)
    assert rule.on_sample() and not rule.answered(4)
    assert rule.diverged() and not rule.active       # the node asks before on_sample
    assert not rule.on_sample()
    assert rule.set_active(True)                     # unbounded: answers y_5 now
    assert not rule.diverged() and not rule.answered(10 ** 6) and rule.active


def test_pre_model_zero_is_clipped_into_the_bounds():
    zero = PreModelInput('zero', ExcitationConfig(), 0, np.array([-1.0, 0.2]),
                         np.array([1.0, 5.0]))
    assert zero.value(7, 0.1).tolist() == [0.0, 0.2]


def test_pre_model_excitation_holds_is_bounded_seeded_and_random_access():
    cfg = ExcitationConfig(kind='random_hold', u_min=(-0.4,), u_max=(0.3,), hold_s=0.5)
    lo, hi = np.array([-1.0]), np.array([1.0])
    seq = PreModelInput('excitation', cfg, 7, lo, hi)
    values = np.array([seq.value(k, 0.1)[0] for k in range(2600)])  # 3 blocks of 1000
    levels = values.reshape(-1, 5)                                # 0.5 s = 5 samples
    assert np.all(levels == levels[:, :1]), 'held for 5 samples from step 0 on'
    assert np.all((values >= -0.4) & (values <= 0.3))
    # Uniform levels: their mean and spread (std of U(-0.4, 0.3) = 0.7/sqrt(12) = 0.202).
    assert abs(levels[:, 0].mean() + 0.05) < 0.03 and abs(levels[:, 0].std() - 0.202) < 0.02
    fresh = PreModelInput('excitation', cfg, 7, lo, hi)
    assert fresh.value(2503, 0.1)[0] == values[2503] and fresh.value(12, 0.1)[0] == values[12]
    other = PreModelInput('excitation', cfg, 8, lo, hi)
    assert [other.value(k, 0.1)[0] for k in range(0, 50, 5)] != values[:50:5].tolist()
    # Another sample time: another hold in samples (0.5 s = 10 samples of 0.05 s).
    fine = np.array([seq.value(k, 0.05)[0] for k in range(40)]).reshape(-1, 10)
    assert np.all(fine == fine[:, :1]) and len(set(fine[:, 0])) == 4


def test_build_model_rejects_models_that_do_not_fit():
    decoded = DecodedWeights(*linearised_vdp_nssm(0.5, 0.1, history=10))
    with pytest.raises(WeightsError, match='n_u = 1, n_y = 2; the plant has 1 input'):
        build_model(decoded, 1, 'manual', 'adapted', MpcConfig(q=(1.0, 0.0, 0.0)), 1, 3)
    with pytest.raises(WeightsError, match='history H = 10, the controller needs 5'):
        build_model(decoded, 1, 'manual', 'adapted', MpcConfig(), 1, 2, history=5)
    bundle = build_model(decoded, 3, 'manual', 'adapted', MpcConfig(), 1, 2, history=10)
    assert (bundle.version, bundle.history) == (3, 10)


def vdp_plant(**fields) -> PlantDescription:
    """plant_info of a lockstep van der Pol plant at dt = 0.1 s, |u| <= 1 (fields override)."""
    return PlantDescription(**{**dict(family='vanderpol', dt=0.1, u_min=(-1.0,),
                                      u_max=(1.0,), n_y=2, lockstep=True), **fields})


def closed_loop(core: ControllerCore, plant: Plant, steps: int, start: int = 0):
    """Run core against the plant core as the node does (theta(k dt) with every y_k);
    returns the TickResults."""
    results = []
    y, u = plant.output(), 0.0
    for k in range(start, start + steps):
        core.observe(k, [u], y, plant.theta)
        res = core.tick()
        results.append(res)
        u = float(res.u[0])
        y = plant.step([u])
    return results


def test_latent_mpc_tracks_a_setpoint_with_the_steady_state_input():
    """x2 = 0, x1 = r is an equilibrium of the plant iff u = r (x2' = -x1 + u): the loop must
    settle there, whatever theta, with the hand-built model linearised at the origin."""
    core = ControllerCore(ControllerConfig(reference_kind='setpoint',
                                           reference_params={'value': 0.6}))
    plant = Plant(PlantConfig(theta=(0.8,)))
    before = closed_loop(core, plant, 3)
    assert [(r.solver_status, r.iterations, r.u[0]) for r in before] == [('no_model', -1, 0.0)] * 3
    core.offer(manual_bundle(version=2, theta=0.8))
    results = closed_loop(core, plant, 80, start=3)
    last = results[-1]
    assert (last.solver_status, last.model_version, last.model_status) == ('solved', 2, 'ok')
    np.testing.assert_allclose(plant.output(), [0.6, 0.0], atol=2e-3)
    assert abs(last.u[0] - 0.6) < 2e-3
    assert last.u_plan.shape == (20, 1) and last.y_pred.shape == last.y_ref.shape == (20, 2)
    np.testing.assert_allclose(last.y_pred[:, 0], 0.6, atol=5e-3)  # it plans to stay there
    assert not any(r.fallback for r in results)

    # Rejected weights: the status says so, the model stays.
    core.refuse(3, 0, 'non-finite weights')
    res = closed_loop(core, plant, 1, start=83)[0]
    assert (res.model_version, res.model_status) == (2, 'rejected: non-finite weights')
    assert [(e.outcome.value, e.version, e.cause.value) for e in res.events] == [
        ('refused', 3, 'weights')]


def test_reference_time_restarts_with_each_episode_and_override():
    """'setpoint_sequence' reference (the paper's task): x1 = 0.8 until 7.5 s, then -0.5;
    times are step * dt."""
    core = ControllerCore(ControllerConfig(mpc=MpcConfig(horizon=2)))
    core.set_plant(vdp_plant())
    plant = Plant(PlantConfig())
    res = closed_loop(core, plant, 76)
    assert res[0].y_ref[:, 0].tolist() == [0.8, 0.8]
    assert res[73].y_ref[:, 0].tolist() == [0.8, -0.5]       # r at 7.4 s and 7.5 s
    assert closed_loop(core, plant, 1)[0].y_ref[:, 0].tolist() == [0.8, 0.8]  # reset: step 0
    assert core.set_override([0.25, 0.0]) == ''
    assert core.references(100).tolist() == [[0.25, 0.0]] * 2
    assert 'expected 2 finite set-points' in core.set_override([0.1])
    assert 'expected 2 finite set-points' in core.set_override([math.nan, 0.0])
    assert core.references(100).tolist() == [[0.25, 0.0]] * 2  # a bad one changes nothing
    assert core.set_override([]) == '' and core.references(75)[0, 0] == -0.5


def test_nmpc_planner_waits_for_plant_info_then_predicts_the_plant():
    """With plant_info's family and the samples' theta, the NMPC's one-step prediction is the
    plant's response (same RK4 model, 2 substeps against the plant's 10: ~1e-6 apart); with
    another theta told by a sample it is not."""
    cfg = ControllerConfig(planner='nmpc', mpc=MpcConfig(horizon=10), reference_kind='setpoint',
                           reference_params={'value': -0.4})
    core = ControllerCore(cfg)
    plant = Plant(PlantConfig(theta=(1.2,), x0=(0.5, 0.5)))
    assert closed_loop(core, plant, 1)[0].solver_status == 'no_plant_info'
    warnings = core.set_plant(vdp_plant(u_min=(-0.5,), u_max=(0.5,)))
    assert len(warnings) == 1 and 'exceed the plant' in warnings[0]
    for k in range(1, 4):
        y_before = plant.output()
        res = closed_loop(core, plant, 1, start=k)[0]
        assert (res.planner, res.solver_status, res.model_version) == ('nmpc', 'solved', 0)
        assert (res.iterations > 0 or k > 1) and np.abs(res.u_plan).max() <= 1.0
        assert res.residual < 1e-8                        # IPOPT's, at its tolerance 1e-10
        np.testing.assert_allclose(res.y_pred[0], plant.output(), atol=1e-5)
        assert np.abs(res.y_pred[0] - y_before).max() > 1e-2   # it did move
    core.observe(4, [float(res.u[0])], plant.output(), (0.0,))
    res = core.tick()
    plant.step(res.u)
    assert np.abs(res.y_pred[0] - plant.output()).max() > 1e-4


def test_the_nmpc_follows_the_samples_theta_under_a_schedule():
    """theta has one channel, the samples (ControllerCore.observe; plant_info tells none): in
    the in-process loop (closed_loop.run_episode) as in the nodes, the NMPC predicts with
    theta(k dt) of the sample it plans from, so under a schedule (a step 0.5 -> -1.0 at 2 s,
    then a ramp to 1.5 over 3-5 s) its one-step prediction stays the plant's response at
    every step. Before, run_episode told the core no theta and the NMPC kept theta 0.5."""
    cfg = ControllerConfig(planner='nmpc', mpc=MpcConfig(horizon=10), reference_kind='setpoint',
                           reference_params={'value': 0.4})
    core = ControllerCore(cfg)
    core.set_plant(vdp_plant())
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.5, 0.0),
                              theta_schedule=(2.0, 2.0, -1.0, 3.0, 5.0, 1.5)))
    episode = run_episode(core, plant, 60)
    assert episode.escaped_at is None
    predicted = np.array([t.y_pred[0] for t in episode.ticks])
    assert np.abs(predicted - episode.y[1:]).max() < 1e-5


def test_the_nmpc_is_built_per_plant_and_tuning_never_per_tick_or_theta(monkeypatch):
    """NMPC constructions counted over ticks whose samples tell a new theta each (a ramp over
    2.5 s): one for the plant and its first theta, one per retune, none per tick, theta or
    episode. A new theta is set_theta on the same NMPC: its warm start and state estimate
    stay, which a rebuild would drop (the tank's unmeasured levels would restart from x0)."""
    built = []
    init = Nmpc.__init__

    def counted(self, *args, **kwargs):
        built.append(self)
        init(self, *args, **kwargs)

    monkeypatch.setattr(Nmpc, '__init__', counted)
    cfg = ControllerConfig(planner='nmpc', mpc=MpcConfig(horizon=10), reference_kind='setpoint',
                           reference_params={'value': 0.4})
    core = ControllerCore(cfg)
    core.set_plant(vdp_plant())
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.5, 0.0), theta_schedule=(0.5, 3.0, 1.5)))
    episode = run_episode(core, plant, 40)
    assert [t.solver_status for t in episode.ticks] == ['solved'] * 40
    assert len(built) == 1 and built[0].theta.tolist() == [1.5]    # the ramp's end
    core.retune(dataclasses.replace(cfg, mpc=MpcConfig(horizon=12)), 1)
    assert len(built) == 2
    again = run_episode(core, plant, 30)      # a new episode, the ramp again
    assert len(built) == 2 and again.ticks[-1].u_plan.shape == (12, 1)


def test_a_sample_theta_that_does_not_fit_leaves_no_nmpc_and_the_loop_goes_on():
    """A y whose theta does not fit the family (two values for van der Pol's one): no NMPC,
    the reason in nmpc_problem, the pre-model input answers; a fitting theta brings the NMPC
    back. A y that tells no theta: the reason says so. Before, the first raised in observe
    (the controller node's callback)."""
    core = ControllerCore(ControllerConfig(planner='nmpc'))
    core.set_plant(vdp_plant())
    core.observe(0, [0.0], [0.3, 0.0], (0.5, 1.0))
    assert 'theta of family vanderpol needs 1 finite value(s)' in core.nmpc_problem
    assert core.tick().solver_status == 'no_plant_info'
    core.observe(1, [0.0], [0.3, 0.0], (0.5,))
    assert core.nmpc_problem == '' and core.tick().solver_status == 'solved'
    untold = ControllerCore(ControllerConfig(planner='nmpc'))
    untold.set_plant(vdp_plant())
    untold.observe(0, [0.0], [0.3, 0.0])
    assert "samples tell no theta" in untold.nmpc_problem
    assert untold.tick().solver_status == 'no_plant_info'


def test_set_plant_warns_about_a_rate_below_the_lockstep_sample_rate():
    core = ControllerCore(ControllerConfig(rate_hz=5.0))
    warnings = core.set_plant(vdp_plant())
    assert len(warnings) == 1 and 'below the lockstep' in warnings[0]
    assert core.set_plant(vdp_plant(lockstep=False)) == []


def test_set_plant_warns_about_a_plant_of_other_dimensions_and_an_unknown_model():
    core = ControllerCore(ControllerConfig(planner='nmpc'))
    tank = PlantDescription('quadruple_tank', 5.0, (0.0, 0.0), (10.0, 10.0), 2, True)
    warnings = core.set_plant(tank)
    assert len(warnings) == 1
    assert 'has 2 input(s) and 2 output(s), this controller 1 and 2' in warnings[0]
    real = dataclasses.replace(vdp_plant(), family='my_robot')
    warnings = core.set_plant(real)
    assert len(warnings) == 1 and "planner nmpc: the plant's model is not available" in (
        warnings[0])
    assert closed_loop(core, Plant(PlantConfig()), 1)[0].solver_status == 'no_plant_info'


@pytest.mark.parametrize('planner', ['latent_mpc', 'nmpc'])
def test_each_episode_starts_cold_whatever_came_before(planner):
    """An episode replays bit for bit whether the core answered other samples before it (the
    previous episode, a stale sample at activation) or not: warm starts, OSQP's duals and its
    adapted rho are reset when a new episode starts. Without the reset the warm-started
    solves differ within the solver tolerance."""
    def episode(core):
        plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, -0.2)))
        return np.array([r.u_plan for r in closed_loop(core, plant, 25)])

    def fresh():
        cfg = ControllerConfig(planner=planner,
                               mpc=MpcConfig(horizon=10, time_limit=NO_TIME_LIMIT),
                               reference_kind='setpoint', reference_params={'value': 0.6})
        core = ControllerCore(cfg)
        core.set_plant(vdp_plant())
        if planner == 'latent_mpc':
            core.offer(manual_bundle(theta=0.5, mpc=cfg.mpc))
        return core

    reference = episode(fresh())
    core = fresh()
    closed_loop(core, Plant(PlantConfig(theta=(-0.4,), x0=(1.0, 1.0))), 30)   # another episode
    core.observe(30, [0.7], [0.9, -0.3])                                      # a stale answer
    core.tick()
    np.testing.assert_array_equal(episode(core), reference)


@pytest.mark.parametrize('planner', ['latent_mpc', 'nmpc'])
def test_retune_applies_from_the_next_tick_as_a_core_started_with_it(planner):
    """A live change between the ticks of steps 11 and 12: from step 12 on the core answers
    bit for bit as a core started with the new tuning that saw the same samples (its planner
    cold at its first tick), with the new horizon, weights, bounds and set-point."""
    def core_with(cfg):
        core = ControllerCore(cfg)
        core.set_plant(vdp_plant())
        if planner == 'latent_mpc':
            core.offer(manual_bundle(theta=0.5, mpc=cfg.mpc))
        return core

    old = ControllerConfig(planner=planner, mpc=MpcConfig(time_limit=NO_TIME_LIMIT),
                           reference_kind='setpoint', reference_params={'value': 0.6})
    new = dataclasses.replace(old, mpc=MpcConfig(horizon=12, r=(0.5,), u_max=(0.4,),
                                                 time_limit=NO_TIME_LIMIT),
                              reference_params={'value': 0.3})
    plant = Plant(PlantConfig(theta=(0.5,)))
    core = core_with(old)
    before = closed_loop(core, plant, 12)
    assert core.check_tuning(new) == ''
    core.retune(new, 1)
    after = closed_loop(core, plant, 10, start=12)

    started = core_with(new)
    sim = Plant(PlantConfig(theta=(0.5,)))      # the samples the retuned core saw
    y, u = sim.output(), 0.0
    for k, res in enumerate(before):
        started.observe(k, [u], y)
        u = float(res.u[0])
        y = sim.step([u])
    again = closed_loop(started, sim, 10, start=12)
    assert [r.config_version for r in before + after] == [0] * 12 + [1] * 10
    assert all(r.u_plan.shape == (12, 1) and r.u[0] <= 0.4 for r in after)
    assert before[-1].y_ref[0, 0] == 0.6 and all(r.y_ref[0, 0] == 0.3 for r in after)
    np.testing.assert_array_equal([r.u_plan for r in after], [r.u_plan for r in again])
    if planner == 'latent_mpc':
        assert core.model.version == 1 and core.model.mpc.config.horizon == 12


def test_check_tuning_refuses_what_the_running_controller_cannot_take():
    core = ControllerCore(ControllerConfig())
    assert core.check_tuning(ControllerConfig(mpc=MpcConfig(u_max=(2.0,)))) == ''  # no plant yet
    core.set_plant(vdp_plant())
    assert core.check_tuning(ControllerConfig(mpc=MpcConfig(u_max=(2.0,)))) == (
        "input bounds [[-1.0], [2.0]] exceed the plant's [[-1.0], [1.0]] (plant_info): a change "
        'must stay within them')
    assert core.check_tuning(ControllerConfig(mpc=MpcConfig(u_max=(0.5,)))) == ''
    wider = ControllerConfig(mpc=MpcConfig(q=(1.0, 0.0, 0.0)), n_y=3)
    assert core.check_tuning(wider) == 'q needs one weight per output (2), got [1.0, 0.0, 0.0]'
    two = ControllerConfig(mpc=MpcConfig(r=(0.1, 0.1)), n_u=2)
    assert core.check_tuning(two).startswith('r, u_min and u_max need one value per input (1)')


def test_a_model_the_offset_free_form_cannot_take_is_refused_and_the_loop_goes_on():
    """A latent mode at eigenvalue 1 that no output sees: an output disturbance cannot be told
    from it (rank test), so the 'output' form refuses the model, and a live change to 'output'
    is refused while that model is in use; the 'state' form takes it and the loop runs."""
    core = ControllerCore(ControllerConfig(reference_kind='setpoint',
                                           reference_params={'value': 0.5}))
    plant = Plant(PlantConfig(theta=(0.5,)))
    output_form = MpcConfig(time_limit=NO_TIME_LIMIT, offset_free='output')
    with pytest.raises(WeightsError, match=r'offset_free output: the disturbance model is not '
                                           r'detectable, rank .* = 4 < n_z \+ n_d = 5 \(A has '
                                           r'an eigenvalue at 1:'):
        manual_bundle(n_z=3, extra_decay=1.0, mpc=output_form)
    core.offer(manual_bundle(version=4, n_z=3, extra_decay=1.0))
    first = closed_loop(core, plant, 60)
    assert core.check_tuning(ControllerConfig(mpc=output_form)).startswith(
        'offset_free output: the disturbance model is not detectable')
    assert core.check_tuning(ControllerConfig(mpc=MpcConfig(offset_free='input'))) == ''
    results = first + closed_loop(core, plant, 60, start=60)
    assert all(r.model_version == 4 and r.solver_status == 'solved' for r in results)
    assert abs(plant.output()[0] - 0.5) < 1e-3


def test_run_episode_is_the_lockstep_loop_replayed_exactly():
    """closed_loop.run_episode against an independent replay: a fresh plant fed the episode's
    inputs gives its outputs bit for bit, each tick's first reference is the reference of the
    next step, and the tracking cost is the experiment's (metrics.tracking_metrics on the
    pairs y_{k+1}, r_{k+1}). A plant that escapes ends the episode at the escape."""
    core = ControllerCore(ControllerConfig(mpc=MpcConfig(time_limit=NO_TIME_LIMIT)))
    core.set_plant(vdp_plant())
    core.offer(manual_bundle(theta=0.5))
    episode = run_episode(core, Plant(PlantConfig(theta=(0.5,))), 120, (0.5,), (0.0, 0.0))
    replay = Plant(PlantConfig(theta=(0.5,)))
    y = [replay.reset((0.5,), (0.0, 0.0))] + [replay.step(u) for u in episode.u[1:]]
    np.testing.assert_array_equal(np.array(y), episode.y)
    assert episode.escaped_at is None and len(episode.ticks) == 120
    refs = core.tuning.reference.evaluate(0.0, 0.1, 120)     # r_1 .. r_120 (from step 0)
    np.testing.assert_allclose(episode.y_ref, refs, atol=1e-12)
    err = episode.y[1:, 0] - refs[:, 0]
    assert episode.tracking_cost([0]) == pytest.approx(float(np.sum(err ** 2)), rel=1e-12)
    # An escape: theta = -1.5 from x0 = (3, 3) with the input held at 0 leaves the box.
    idle = ControllerCore(ControllerConfig(active=True))
    idle.set_plant(vdp_plant())
    escaped = run_episode(idle, Plant(PlantConfig(theta=(-1.5,))), 300, (-1.5,), (3.0, 3.0))
    assert escaped.escaped_at is not None and len(escaped.y) == escaped.escaped_at + 1


def test_run_episode_warmup_noise_and_reference_table():
    """Online collection's hooks (closed_loop.run_episode, ControllerCore.set_references),
    against a replay of the episode: the plant holds the W warm-up inputs while the core only
    observes; then each input is the tick's answer plus its noise row, clipped by the plant;
    every later tick plans from the input the plant held (u_prev: the MPC's plan is
    recomputed on a fresh planner with the clipped inputs and must be the tick's), towards
    rows t + 1..t + N of the table (an override wins over it)."""
    mpc = MpcConfig(horizon=4, time_limit=NO_TIME_LIMIT)
    core = ControllerCore(ControllerConfig(mpc=mpc))
    bundle = manual_bundle(theta=0.5, history=3, mpc=mpc)
    core.offer(bundle)
    rng = np.random.default_rng(1)
    table = np.column_stack([rng.uniform(-0.8, 0.8, 50), np.zeros(50)])
    core.set_references(table)
    warmup, noise = rng.uniform(-1.0, 1.0, (3, 1)), rng.normal(0.0, 0.7, (37, 1))
    episode = run_episode(core, Plant(PlantConfig(theta=(0.5,))), 40, (0.5,), (0.5, 0.0),
                          warmup, noise)
    assert episode.escaped_at is None and len(episode.ticks) == 37
    np.testing.assert_array_equal(episode.u[1:4], warmup)
    assert np.all(np.isnan(episode.y_ref[:3]))
    clipped = np.clip([t.u + e for t, e in zip(episode.ticks, noise)], -1.0, 1.0)
    np.testing.assert_array_equal(episode.u[4:], clipped)
    assert np.any(np.abs(clipped) == 1.0) and np.any(np.abs(clipped) < 1.0)   # both cases
    replay = manual_bundle(theta=0.5, history=3, mpc=mpc)
    u, y = episode.u, episode.y
    for i, tick in enumerate(episode.ticks):
        t = 3 + i
        np.testing.assert_array_equal(tick.y_ref, table[t + 1:t + 5])
        z = replay.predictor.encode(u[t - 2:t + 1], y[t - 2:t + 1])
        plan = replay.mpc.solve(z, u[t], table[t + 1:t + 5], y[t], t)
        np.testing.assert_array_equal(tick.u_plan, plan.u_plan)
    assert core.set_override([0.25, 0.0]) == ''
    assert core.references(5).tolist() == [[0.25, 0.0]] * 4
    assert core.set_override([]) == '' and np.array_equal(core.references(5), table[6:10])
    with pytest.raises(ValueError, match='step 46 needs rows up to 50'):
        core.references(46)
    with pytest.raises(ValueError, match='finite'):
        core.set_references(np.zeros((10, 3)))
    core.set_references(None)
    assert core.references(0)[0, 0] == 0.8      # the tuning's reference again


def test_history_rows_are_the_samples_of_the_episode():
    rng = np.random.default_rng(0)
    for capacity in (1, 2, 7):
        hist = History(capacity, n_u=1, n_y=2)
        episode, step = [], -1
        for _ in range(400):
            step = step + 1 if rng.random() > 0.05 else int(rng.integers(0, 20))
            u, y = rng.normal(size=1), rng.normal(size=2).tolist()
            if hist.append(step, u, y):
                episode = []
            episode.append((u.tolist(), y))
            for h in range(1, capacity + 1):
                rows = [episode[max(j, 0)] for j in range(len(episode) - h, len(episode))]
                u_win, y_win = hist.window(h)
                assert u_win.tolist() == [r[0] for r in rows]
                assert y_win.tolist() == [r[1] for r in rows]


def _capped_loop(cap: float, plant_at: int, lockstep: bool, reset_at: int = -1, steps=30):
    """A core (OSQP time_limit `cap` s) on the plant core, told plant_info (lockstep or real
    time) before the tick of `plant_at` (0: before the model's first tick), the plant reset at
    `reset_at`; the tick results."""
    mpc = MpcConfig(time_limit=cap)
    core = ControllerCore(ControllerConfig(reference_kind='setpoint', mpc=mpc,
                                           reference_params={'value': 0.5}))
    core.offer(manual_bundle(mpc=mpc))
    plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, 0.0)))
    y, u, out, k = plant.output(), 0.0, [], 0
    for i in range(steps):
        if i == plant_at:
            core.set_plant(vdp_plant(lockstep=lockstep))
        if i == reset_at:
            y, u, k = plant.reset(), 0.0, 0
        core.observe(k, [u], y)
        res = core.tick()
        out.append(res)
        u = float(res.u[0])
        y, k = plant.step([u]), k + 1
    return out


def test_a_lockstep_plant_lifts_osqp_s_wall_clock_cap_in_place():
    """A cap of 1 ns trips every solve of a real-time plant (the fallback); told that the
    plant is lockstep, before the first tick or after five, the controller solves every tick
    from then on, a plant reset (a cold planner) included, since the cap is lifted in the
    planner itself. Under the default cap, plans are the same bit for bit whether plant_info
    came before the model's first tick or after it (a rebuilt planner would start cold)."""
    capped = _capped_loop(1e-9, 0, lockstep=False)
    assert all(r.fallback and r.solver_status != 'solved' for r in capped)
    for plant_at in (0, 5):
        lifted = _capped_loop(1e-9, plant_at, lockstep=True, reset_at=20)
        assert all(r.fallback for r in lifted[:plant_at])
        assert all(r.solver_status == 'solved' and not r.fallback for r in lifted[plant_at:])
    before, after = (_capped_loop(NO_TIME_LIMIT, at, lockstep=True) for at in (0, 1))
    assert all(np.array_equal(a.u_plan, b.u_plan) for a, b in zip(before, after))
