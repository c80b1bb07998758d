"""The `plant` node as a process (`ros2 run metampc_plant plant`) in the session's own domain.

The probe node of the test plays the controller: it answers y_k with a ControlInput for k.
"""
import math
import time

from builtin_interfaces.msg import Time
from family_equations import OUTPUT_GAIN, one_step
from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput
from metampc_msgs.srv import ResetPlant
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from metampc_plant.plant_params import parse_params, ParameterError, PARAMETERS
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig
from metampc_testing import own_lines, session_pids

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
NAN, INF = float('nan'), float('inf')


def ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def seconds(first: PlantOutput, last: PlantOutput) -> float:
    """Time between two samples' stamps, s."""
    return (ns(last.header.stamp) - ns(first.header.stamp)) / 1e9


def start_plant(procs, params):
    return procs.start('metampc_plant', 'plant', params=params)


def stop_cleanly(procs, proc) -> str:
    """SIGINT the plant: exit 0, no traceback, nothing left running; return its output."""
    code = procs.interrupt(proc)
    out = procs.output(proc)
    assert code == 0, out
    assert 'Traceback' not in out, out
    assert session_pids(proc) == [], 'a process of the plant outlived ros2 run'
    return out


class Controller:
    """Probe-side controller: `policy(y_msg)` gives the ControlInputs to send for each y."""

    def __init__(self, probe, policy):
        self.ys = []
        self.policy = policy
        self.pub = probe.node.create_publisher(ControlInput, 'u', RELIABLE)
        probe.node.create_subscription(PlantOutput, 'y', self._on_y, RELIABLE)

    def _on_y(self, msg: PlantOutput) -> None:
        self.ys.append(msg)
        for step, u in self.policy(msg):
            self.pub.publish(ControlInput(step=step, u=u))


def u_of(k: int) -> float:
    """A deterministic input sequence that exceeds |u| <= 1 now and then."""
    return 1.3 * math.sin(0.05 * k)


def test_lockstep_one_y_per_input_and_bit_exact(procs, probe):
    n = 500
    cfg = PlantConfig(theta=(0.7,), dt=0.05, x0=(0.5, -0.2), process_noise_std=0.05,
                      measurement_noise_std=0.01, seed=42)
    clocks, infos = [], []
    probe.node.create_subscription(Clock, '/clock', lambda m: clocks.append(ns(m.clock)),
                                   RELIABLE)
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    ctl = Controller(probe, lambda m: [(m.step, [u_of(m.step)])] if m.step < n else [])
    # A long input_timeout: every step below must have been answered, none timed out.
    proc = start_plant(procs, {
        'theta': list(cfg.theta), 'dt': cfg.dt, 'x0': list(cfg.x0), 'seed': cfg.seed,
        'process_noise_std': cfg.process_noise_std,
        'measurement_noise_std': cfg.measurement_noise_std, 'input_timeout': 30.0})
    probe.wait_for(lambda: len(ctl.ys) > n and clocks and clocks[-1] == n * 50_000_000, 60.0,
                   f'{n} answered steps')
    time.sleep(0.3)
    ys = ctl.ys
    assert [m.step for m in ys] == list(range(n + 1)), 'one y per answered input, in order'
    assert [ns(m.header.stamp) for m in ys] == [k * 50_000_000 for k in range(n + 1)]
    # /clock: y_k's stamp, advancing by exactly dt (the first ticks may precede discovery).
    assert len(clocks) >= n - 5 and clocks[-1] == n * 50_000_000
    assert set(np.diff(clocks)) == {50_000_000}

    # Same seed, same inputs: the node reproduces the core bit for bit.
    plant = Plant(cfg)
    expected = [plant.output()] + [plant.step([u_of(k)]) for k in range(n)]
    assert np.array_equal(np.array([list(m.y) for m in ys]), np.array(expected))
    u_expected = [0.0] + [min(max(u_of(k), -1.0), 1.0) for k in range(n)]
    assert [m.u_applied[0] for m in ys] == u_expected
    assert [m.saturated for m in ys] == [False] + [abs(u_of(k)) > 1.0 for k in range(n)]
    assert not any(m.diverged for m in ys)

    info = infos[-1]
    assert (info.family, list(info.theta), info.dt, info.substeps, info.seed) == (
        'vanderpol', [0.7], 0.05, 10, 42)
    assert (list(info.u_min), list(info.u_max), list(info.output_names),
            list(info.input_names), list(info.theta_names)) == (
        [-1.0], [1.0], ['x1', 'x2'], ['u'], ['theta'])
    assert (info.clock_mode, info.rate_hz, info.diverged, info.n_resets) == ('lockstep', 0.0,
                                                                             False, 0)
    out = stop_cleanly(procs, proc)
    assert '0 stale, 0 rejected, 0 timeouts' in out, out


FAMILY_RUNS = {  # family: (theta, x0), a target drawn by hand from each prior
    'vanderpol': ([0.8], [0.5, -0.2]),
    'duffing': ([0.2, -0.6, 1.1], [0.3, 0.0]),
    'pendulum': ([0.9, 1.2, 0.1], [0.4, 0.0]),
    'quadruple_tank': ([0.7, 0.4], [12.4, 12.7, 1.8, 1.4]),
    'cascaded_tanks': ([0.06, 0.03, 0.03, 0.045, 0.015], [3.0, 3.0]),   # below the rims
}


@pytest.mark.parametrize('name', sorted(FAMILY_RUNS))
def test_lockstep_node_matches_scipy_for_each_family(procs, probe, name):
    """The node in lockstep, answered with a known input sequence within the bounds, against
    scipy (DOP853, rtol 1e-12) of the equations in test/family_equations.py: each y_{k+1}
    within 1e-6 of the one-step integration from y_k (y = x families), or, for the quadruple
    tank whose tank 3 and 4 levels are not measured, of the reference integrated along the
    whole input sequence from x0."""
    n = 40
    family = get_family(name)
    theta, x0 = FAMILY_RUNS[name]
    levels = np.random.default_rng(5).uniform(family.u_min, family.u_max,
                                              size=(n // 5, family.n_u))
    inputs = np.repeat(levels, 5, axis=0)
    ctl = Controller(probe, lambda m: [(m.step, list(inputs[m.step]))] if m.step < n else [])
    proc = start_plant(procs, {'family': name, 'theta': theta, 'x0': x0, 'input_timeout': 30.0})
    probe.wait_for(lambda: len(ctl.ys) > n, 60.0, f'{n} answered steps of {name}')
    ys = np.array([list(m.y) for m in ctl.ys[:n + 1]])
    assert [m.step for m in ctl.ys[:n + 1]] == list(range(n + 1))
    dt = family.dt
    gain = OUTPUT_GAIN.get(name, np.eye(family.n_x))
    x_ref = np.asarray(x0, dtype=float)
    worst = 0.0
    for k in range(n):
        start = ys[k] if name in ('vanderpol', 'duffing', 'pendulum') else x_ref
        x_ref = one_step(name, start, inputs[k], theta, dt)
        worst = max(worst, np.abs(ys[k + 1] - gain @ x_ref).max())
        assert list(ctl.ys[k + 1].u_applied) == list(inputs[k])
    assert worst < 1e-6, f'{name}: worst error {worst:.2e}'
    stop_cleanly(procs, proc)


def test_start_gate_waits_for_the_named_number_of_subscribers(procs, probe):
    """start_subscribers 2 (a controller and a recorder): with one subscriber on y y_0 does not
    go out; once a second one subscribes, the first y both receive is y_0."""
    ctl = Controller(probe, lambda m: [(m.step, [0.1])] if m.step < 20 else [])
    proc = start_plant(procs, {'start_subscribers': 2, 'start_timeout': 0.0,
                               'input_timeout': 30.0})
    probe.wait_for(lambda: 'subscriber(s)' in procs.output(proc), 60.0, 'the plant up')
    time.sleep(2.0)     # the gate settles in well under a second once matched
    assert ctl.ys == []
    recorded = []
    probe.node.create_subscription(PlantOutput, 'y', recorded.append, RELIABLE)
    probe.wait_for(lambda: len(ctl.ys) > 20 and len(recorded) > 20, 60.0, '20 steps')
    assert ctl.ys[0].step == 0 and recorded[0].step == 0
    stop_cleanly(procs, proc)


def test_lockstep_bad_and_stale_inputs_and_timeout(procs, probe):
    script = {  # y_k -> the inputs sent in reply, in order
        0: [(5, [0.2]), (0, [0.3])],     # an input for another step is stale: ignored
        1: [(1, [NAN])],                 # rejected: the previous input (0.3) is held
        2: [(2, [INF])],
        3: [(3, [])],                    # wrong length
        4: [(4, [0.1, 0.2])],
        5: [(5, [5.0])],                 # saturated to u_max
        6: [(5, [0.0]), (6, [-3.0])],    # stale (older step), then saturated to u_min
        7: [],                           # no answer: after input_timeout the input is held
        8: [(8, [0.25])],
    }
    ctl = Controller(probe, lambda m: script.get(m.step, []))
    proc = start_plant(procs, {'theta': 1.0, 'x0': [1.0, 0.0], 'input_timeout': 0.5})
    probe.wait_for(lambda: len(ctl.ys) >= 10, 30.0, 'y_9')
    ys = ctl.ys[:10]
    assert [m.step for m in ys] == list(range(10))
    assert [m.u_applied[0] for m in ys[1:]] == [0.3, 0.3, 0.3, 0.3, 0.3, 1.0, -1.0, -1.0, 0.25]
    assert [m.saturated for m in ys[1:]] == [False] * 5 + [True, True, False, False]
    assert all(np.isfinite(m.y).all() for m in ctl.ys)
    assert proc.poll() is None
    out = stop_cleanly(procs, proc)
    assert 'ignored an input for step 5: waiting for step 0' in out
    assert 'rejected the input for step 1 (non-finite input [nan])' in out
    assert 'no input for step 7 within 0.5 s' in out
    assert '2 stale, 4 rejected' in out, out


def test_real_time_factor_paces_the_lockstep_loop(procs, probe):
    """real_time_factor 1: each y at least dt of wall time after the previous one (a session
    by hand runs at its sample rate; before: as fast as the answers came), with the same
    steps, inputs, outputs and stamps as unpaced; a second answer to a step that the pace
    holds back is stale, as it is once the plant has stepped."""
    n, dt = 60, 0.05
    heard = []

    def policy(m):
        heard.append(time.monotonic())
        if m.step >= n:
            return []
        return [(m.step, [u_of(m.step)])] + ([(m.step, [0.9])] if m.step == 5 else [])

    ctl = Controller(probe, policy)
    proc = start_plant(procs, {'theta': 0.7, 'dt': dt, 'x0': [0.5, -0.2],
                               'input_timeout': 30.0, 'real_time_factor': 1.0})
    probe.wait_for(lambda: len(ctl.ys) > n, 60.0, f'{n} answered steps')
    ys = ctl.ys[:n + 1]
    assert [m.step for m in ys] == list(range(n + 1))
    assert [ns(m.header.stamp) for m in ys] == [k * 50_000_000 for k in range(n + 1)]
    plant = Plant(PlantConfig(theta=(0.7,), dt=dt, x0=(0.5, -0.2)))
    expected = [plant.output()] + [plant.step([u_of(k)]) for k in range(n)]
    assert np.array_equal(np.array([list(m.y) for m in ys]), np.array(expected))
    # n steps took at least n dt of wall time; the probe hears a y late by its delivery
    # (under load tens of ms), which the margin covers. Unpaced they take ~0.2 s here.
    span = heard[n] - heard[0]
    assert span >= n * dt - 0.25, f'{n} steps in {span:.2f} s'
    out = stop_cleanly(procs, proc)
    assert 'at most 1x real time' in out, out
    assert 'ignored an input for step 5: waiting for step 5 (answered)' in out, out
    assert '1 stale, 0 rejected, 0 timeouts' in out, out


def test_realtime_rate_and_held_input(procs, probe):
    rate, span = 50, 5.0
    ctl = Controller(probe, lambda m: [])
    # rate_hz as an integer on purpose: numbers are accepted for double parameters.
    proc = start_plant(procs, {'mode': 'realtime', 'rate_hz': rate, 'dt': 0.02,
                               'theta': 1.0, 'x0': [1.0, 0.0]})
    probe.wait_for(lambda: len(ctl.ys) > 5, 30.0, 'realtime samples')
    ctl.pub.publish(ControlInput(step=0, u=[0.4]))  # the step is irrelevant in realtime
    probe.wait_for(lambda: ctl.ys[-1].u_applied[0] == 0.4, 30.0, 'the input applied')
    held_from = next(i for i, m in enumerate(ctl.ys) if m.u_applied[0] == 0.4)
    ctl.pub.publish(ControlInput(u=[NAN]))
    ctl.pub.publish(ControlInput(u=[0.1, 0.2]))
    probe.wait_for(lambda: 'rejected the input' in procs.output(proc), 30.0, 'a rejection')
    # Ticks after the rejections (they must hold 0.4), and span s of samples for the rate.
    n = len(ctl.ys)
    probe.wait_for(lambda: len(ctl.ys) >= n + 20 and seconds(ctl.ys[0], ctl.ys[-1]) >= span,
                   60.0, f'{span} s of samples')
    # Inputs on one topic arrive in order: once -7 is applied, both bad ones were handled.
    ctl.pub.publish(ControlInput(u=[-7.0]))
    probe.wait_for(lambda: ctl.ys[-1].saturated and ctl.ys[-1].u_applied[0] == -1.0, 30.0,
                   'a saturated sample')
    ys = list(ctl.ys)
    held = ys[held_from:next(i for i, m in enumerate(ys) if m.saturated)]
    assert all(m.u_applied[0] == 0.4 and not m.saturated for m in held), 'input held'
    steps = [m.step for m in ys]
    assert steps == list(range(steps[0], steps[0] + len(steps)))
    # The rate on the plant's own wall-clock stamps, not on when the probe heard the samples.
    # A loaded machine only makes ticks late (rcl then skips the missed ones), never early.
    measured = (steps[-1] - steps[0]) / seconds(ys[0], ys[-1])
    assert rate / 2 <= measured <= rate * 1.05, f'{measured:.1f} Hz'
    # Stamped with the wall clock (sim time would start at 0).
    assert abs(ns(ys[-1].header.stamp) / 1e9 - time.time()) < 60.0, 'wall-clock stamps'
    out = stop_cleanly(procs, proc)
    assert '0 stale, 2 rejected' in out, out


def call(probe, client, theta=(), x0=(), resend_every=None):
    return probe.call(client, ResetPlant.Request(theta=list(theta), x0=list(x0)), 10.0,
                      resend_every)


def test_divergence_flagged_then_reset(procs, probe):
    phase = {'drive': True}

    def policy(m):
        # Bang-bang in phase with x2 pumps energy into the theta < 0 plant until it escapes.
        u = (1.0 if m.y[1] >= 0 else -1.0) if phase['drive'] else 0.0
        return [(m.step, [u])]

    ctl = Controller(probe, policy)
    client = probe.node.create_client(ResetPlant, 'reset')
    proc = start_plant(procs, {'theta': -1.5, 'dt': 0.1, 'x0': [0.5, 0.0],
                               'state_bound': 10.0, 'input_timeout': 5.0})
    probe.wait_for(lambda: any(m.diverged for m in ctl.ys), 30.0, 'divergence')
    first = next(i for i, m in enumerate(ctl.ys) if m.diverged)
    probe.wait_for(lambda: len(ctl.ys) > first + 5, 10.0, 'samples after divergence')
    ys = list(ctl.ys)
    assert all(np.isfinite(m.y).all() and np.abs(m.y).max() <= 10.0 for m in ys)
    assert all(m.diverged for m in ys[first:]), 'diverged holds until reset'
    assert all(list(m.y) == list(ys[first - 1].y) for m in ys[first:]), 'frozen, last finite'

    # plant_info is latched: a subscriber that comes now still learns of the divergence.
    infos = []
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    probe.wait_for(lambda: infos and infos[-1].diverged, 10.0, 'plant_info diverged')

    assert client.wait_for_service(timeout_sec=10.0)
    # Rejected resets change nothing: resent while unanswered (a first answer can be lost,
    # SpunNode.call).
    for bad in [dict(x0=[1.0, 2.0, 3.0]), dict(x0=[NAN, 0.0]), dict(theta=[INF]),
                dict(theta=[0.5, 0.5]), dict(x0=[20.0, 0.0]), dict(theta=[9.0])]:
        result = call(probe, client, **bad, resend_every=3.0)
        assert not result.success and result.message.startswith('reset rejected'), bad
    assert 'theta = 9 lies outside the range [-4, 4]' in result.message, result.message
    assert proc.poll() is None

    phase['drive'] = False
    n_before = len(ctl.ys)
    result = call(probe, client, theta=[0.5], x0=[0.5, 0.0])
    assert result.success, result.message
    probe.wait_for(lambda: any(m.step == 5 and not m.diverged for m in ctl.ys[n_before:]),
                   10.0, 'the first steps after the reset')
    after = [m for m in ctl.ys[n_before:] if not m.diverged]
    assert [m.step for m in after[:6]] == list(range(6))
    assert list(after[0].y) == [0.5, 0.0] and list(after[0].u_applied) == [0.0]
    probe.wait_for(lambda: not infos[-1].diverged, 10.0, 'plant_info after the reset')
    assert (infos[-1].n_resets, list(infos[-1].theta)) == (1, [0.5])
    out = stop_cleanly(procs, proc)
    assert out.count('plant diverged at step') == 1, out


def test_plant_alone_keeps_stepping_in_a_namespace(procs, probe):
    # No controller: after start_timeout y_0 goes out anyway and every step times out.
    # Relative names: in namespace /ns1 the topics are /ns1/y ..., but /clock stays global.
    ys, clocks = [], []
    probe.node.create_subscription(PlantOutput, '/ns1/y', ys.append, RELIABLE)
    probe.node.create_subscription(Clock, '/clock', clocks.append, RELIABLE)
    proc = procs.start('metampc_plant', 'plant', remaps={'__ns': '/ns1'},
                       params={'start_timeout': 0.5, 'input_timeout': 0.2})
    probe.wait_for(lambda: len(ys) >= 5 and clocks, 30.0, 'five samples without a controller')
    # Discovery may take a few seconds: the probe may join after y_0.
    steps = [m.step for m in ys]
    assert steps == list(range(steps[0], steps[0] + len(steps)))
    assert all(list(m.u_applied) == [0.0] for m in ys)
    out = stop_cleanly(procs, proc)
    assert 'no input for step 0 within 0.2 s; holding u = [0.0]' in out


def test_sigint_while_stepping_fast(procs, probe):
    # rclpy's signal thread shuts the context down while a callback may be publishing;
    # the plant must still exit 0 without a traceback.
    ctl = Controller(probe, lambda m: [(m.step, [0.1])])
    for _ in range(2):
        ctl.ys.clear()
        proc = start_plant(procs, {'input_timeout': 0.0})
        probe.wait_for(lambda: len(ctl.ys) > 300, 30.0, 'fast lockstep steps')
        stop_cleanly(procs, proc)


BAD_PARAMS = {
    'dt': ({'dt': -0.1}, 'dt must be >= 0'),
    'substeps': ({'substeps': 0}, 'substeps'),
    'bounds': ({'u_min': 2.0}, 'u_min <= u_max'),
    'mode': ({'mode': 'fast'}, 'mode must be one of'),
    'x0': ({'x0': [1.0]}, 'x0 of family vanderpol needs 2 values'),
    'family': ({'family': 'tank'}, "unknown plant family 'tank'; installed: cascaded_tanks, "
                                   'duffing'),
    'theta': ({'family': 'duffing', 'theta': [0.1]}, 'theta of family duffing needs 3'),
    # One range check wherever theta enters (before: only a schedule's rows had one).
    'range': ({'theta': 9.0}, 'theta: theta = 9 lies outside the range [-4, 4] of family '
                              'vanderpol'),
    'wide': ({'family': 'pendulum', 'u_max': 5.0}, 'outside those of family pendulum'),
    'rate': ({'rate_hz': -5.0}, 'rate_hz'),
    'timeout': ({'input_timeout': -1.0}, 'input_timeout'),
    'type': ({'theta': 'abc'}, 'theta must be a list of numbers'),
    'start': ({'start_timeout': -1}, 'start_timeout'),
    # Not even parsed by rcl (YAML lists hold one type): rcl logs a generic line first.
    'yaml': ({'x0': [1, 0.5]}, 'invalid arguments: Couldn\'t parse parameter override rule'),
}


def test_bad_parameters_one_line_and_nonzero_exit(procs):
    started = {case: start_plant(procs, params) for case, (params, _) in BAD_PARAMS.items()}
    for case, proc in started.items():
        code = proc.wait(60.0)
        lines = own_lines(procs.output(proc))
        assert code != 0, case
        assert len(lines) == (2 if case == 'yaml' else 1), f'{case}: {lines}'
        assert BAD_PARAMS[case][1] in lines[-1], lines
        assert case == 'yaml' or 'invalid parameter' in lines[0], lines


def _raw(**overrides):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(overrides)
    return values


def test_parse_params_defaults_and_coercion():
    cfg = parse_params(_raw())
    assert cfg.plant == PlantConfig(theta=(0.0,), dt=0.1, x0=(0.0, 0.0), u_min=(-1.0,),
                                    u_max=(1.0,), state_bound=10.0)
    assert cfg.mode == 'lockstep' and cfg.sample_rate_hz() == 1 / cfg.plant.dt
    cfg = parse_params(_raw(dt=1, x0=[1, 0], rate_hz=50, mode='realtime', start_timeout=0,
                            theta=0.5))
    assert cfg.plant.dt == 1.0 and cfg.plant.x0 == (1.0, 0.0) and cfg.rate_hz == 50.0
    assert cfg.plant.theta == (0.5,), 'a lone number is a theta of one component'
    assert cfg.start_timeout == 0.0 and cfg.input_timeout == 1.0
    cfg = parse_params(_raw(family='quadruple_tank', u_max=[5, 6]))
    assert (cfg.plant.u_min, cfg.plant.u_max, cfg.plant.dt) == ((0.0, 0.0), (5.0, 6.0), 5.0)


@pytest.mark.parametrize('overrides,match', [
    ({'substeps': 2.5}, 'substeps must be an integer'), ({'seed': -1}, 'seed'),
    ({'publish_clock': 1}, 'publish_clock'), ({'x0': [20.0, 0.0]}, 'state_bound'),
    ({'x0': 'ab'}, 'x0'), ({'input_timeout': INF}, 'input_timeout'),
    ({'measurement_noise_std': -0.1}, 'noise'), ({'theta': True}, 'theta')])
def test_parse_params_rejects(overrides, match):
    with pytest.raises(ParameterError, match=match):
        parse_params(_raw(**overrides))


def test_theta_schedule_in_lockstep_lands_at_exact_steps(procs, probe):
    """theta_schedule: a step to -0.5 at t = 1 s and a ramp to 1.5 over [2, 3] s (dt = 0.1 s).
    Each y_k carries theta(k dt): the start value up to y_9, -0.5 from y_10 (the sample from
    step 10 on is integrated with it), then the ramp by np.interp over the plant time; and
    each y_{k+1} is scipy's one step from y_k with y_k's theta (1e-6). plant_info is re-sent as
    segments start and end; a reset with a schedule out of range is refused, the plant goes on.
    """
    n, theta0 = 40, 0.5
    schedule = [1.0, 1.0, -0.5, 2.0, 3.0, 1.5]
    infos = []
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    ctl = Controller(probe, lambda m: [(m.step, [u_of(m.step)])] if m.step < n else [])
    proc = start_plant(procs, {'theta': theta0, 'x0': [1.0, 0.0], 'input_timeout': 30.0,
                               'theta_schedule': schedule})
    probe.wait_for(lambda: len(ctl.ys) > n, 60.0, f'{n} answered steps')
    ys = ctl.ys[:n + 1]
    # theta(k dt), independently by interpolation of the schedule's breakpoints.
    expected = [theta0 if t < 1.0 else float(np.interp(t, [2.0, 3.0], [-0.5, 1.5]))
                for t in 0.1 * np.arange(n + 1)]
    got = [m.theta[0] for m in ys]
    assert got[:10] == [theta0] * 10 and got[10:21] == [-0.5] * 11
    assert np.allclose(got, expected, rtol=0, atol=1e-12), got
    worst = max(np.abs(np.array(ys[k + 1].y) - one_step(
        'vanderpol', np.array(ys[k].y), [min(max(u_of(k), -1.0), 1.0)], [got[k]], 0.1)
    ).max() for k in range(n))
    assert worst < 1e-6, f'worst error {worst:.2e}'
    # Re-sent at t = 1 (step), 2 (ramp starts), 3 (ramp ends); the latest says 1.5.
    probe.wait_for(lambda: infos and infos[-1].theta[0] == 1.5, 10.0, 'plant_info after ramp')
    assert list(infos[-1].theta_schedule) == schedule

    reset = probe.node.create_client(ResetPlant, 'reset')
    assert reset.wait_for_service(timeout_sec=10.0)
    request = ResetPlant.Request(theta=[0.5], theta_schedule=[5.0, 5.0, 9.0])
    result = probe.call(reset, request, 10.0, resend_every=3.0)
    assert not result.success and 'theta = 9 lies outside the range [-4, 4]' in result.message
    assert proc.poll() is None
    stop_cleanly(procs, proc)
