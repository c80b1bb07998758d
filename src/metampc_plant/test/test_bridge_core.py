"""The bridge's rules on a made-up timeline: a machine sampling every 0.04 s with its own
stamps, ticks every 0.1 s, a controller answering each step; y_k, u_applied_k and the command
against values worked out from the stamps, and the safe value when the machine or the
controller falls silent."""
import dataclasses
import math
import os

from metampc_plant.bridge_core import BridgeCore, DROPPED, FOLLOWING, OFFSET, STALE, WAITING
from metampc_plant.machine_mapping import load_mapping
import pytest
from sensor_msgs.msg import JointState

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(
    __file__)))))
MAPPING = load_mapping(os.path.join(ROOT, 'examples', 'joint_robot', 'mapping.yaml'))
PERIOD = 0.04       # the machine's sample period, s
LATENCY = 0.001     # from its stamp to the bridge, s
T0 = 100.002        # the first tick (the timer fires 2 ms into the machine's period)


def joints(stamp: float, position: float) -> JointState:
    msg = JointState(position=[position], velocity=[-position])
    ns = round(stamp * 1e9)
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 10**9, ns % 10**9
    return msg


class Timeline:
    """The bridge under a machine that publishes sample i at i * PERIOD (position = its stamp,
    so a value names its sample) until `silent_from`, and ticks at T0 + k dt."""

    def __init__(self):
        self.core = BridgeCore(MAPPING)
        self.next_sample = math.ceil(T0 / PERIOD) - 5
        self.silent = (math.inf, math.inf)   # no samples stamped in [start, end)

    def until(self, now: float) -> None:
        """Deliver every sample that has arrived by `now`."""
        while self.next_sample * PERIOD + LATENCY <= now:
            stamp = self.next_sample * PERIOD
            if not self.silent[0] <= stamp < self.silent[1]:
                assert self.core.sample(0, joints(stamp, stamp), stamp + LATENCY) == ('', '')
            self.next_sample += 1

    def tick(self, k: int):
        now = T0 + k * MAPPING.dt
        self.until(now)
        return self.core.tick(now)


def newest_stamp(t: float) -> float:
    """By hand: the machine's newest stamp at or before t."""
    return math.floor(t / PERIOD + 1e-9) * PERIOD


def test_y_is_the_newest_sample_and_the_command_follows_each_answer_clipped():
    line = Timeline()
    first = line.tick(0)
    assert (first.step, first.state, first.previous, first.reason) == (
        0, WAITING, '', 'no input from the controller yet')
    assert first.write.tolist() == [0.0] and first.u_applied.tolist() == [0.0]
    assert line.core.answer(1, [0.5], T0 + 0.01).why.startswith('step 1 is not one published')
    answer = line.core.answer(0, [2.0], T0 + 0.01)      # beyond max 1: clipped
    assert answer.write.tolist() == [1.0] and answer.resumed and line.core.state == FOLLOWING
    assert line.core.answer(0, [0.5], T0 + 0.02).why == 'step 0 was answered already'
    for k in range(1, 6):
        tick = line.tick(k)
        t_k = T0 + k * MAPPING.dt
        assert tick.time == pytest.approx(t_k, abs=1e-9)
        assert tick.y.tolist() == pytest.approx([newest_stamp(t_k), -newest_stamp(t_k)])
        assert tick.ages[0] == pytest.approx(t_k - newest_stamp(t_k))
        # The input written after y_{k-1} (the answer to step k-1) is held over (k-1, k].
        assert tick.u_applied.tolist() == ([1.0] if k == 1 else [0.1 * (k - 1)])
        assert tick.saturated == (k == 1)
        assert (tick.state, tick.write, tick.changed) == (FOLLOWING, None, False)
        answer = line.core.answer(k, [0.1 * k], t_k + 0.01)
        assert answer.write.tolist() == [pytest.approx(0.1 * k)] and not answer.resumed
    assert line.core.answer(6, [float('nan')], T0 + 0.6).why.startswith('step 6 is not one')
    line.tick(6)
    assert line.core.answer(6, [float('nan')], T0 + 0.61).why == (
        'expected 1 finite value(s), got [nan]')
    assert line.core.answer(6, [0.1, 0.2], T0 + 0.61).why.startswith('expected 1 finite')


def test_a_silent_machine_gets_the_safe_value_within_stale_timeout_plus_dt_until_it_is_back():
    line = Timeline()
    line.tick(0)
    line.core.answer(0, [0.5], T0 + 0.01)
    last = newest_stamp(T0 + 0.45)           # the machine's last sample before it stalls
    assert last == pytest.approx(100.44)
    line.silent = (last + PERIOD / 2, T0 + 1.5)
    states = []
    for k in range(1, 20):
        tick = line.tick(k)
        states.append(tick.state)
        if tick.state == FOLLOWING:
            line.core.answer(k, [0.5], tick.time + 0.01)
    # By hand: the last sample is stamped 100.44; the first tick whose held sample is older
    # than stale_timeout is k = 8 (t = 100.802, age 0.362 s); the machine is back with the
    # sample stamped 101.52, first held at k = 16 (t = 101.602): then waiting for an answer.
    assert states == [FOLLOWING] * 7 + [STALE] * 8 + [WAITING] * 4
    assert MAPPING.stale_timeout < T0 + 0.8 - last <= MAPPING.stale_timeout + MAPPING.dt
    core = line.core
    assert core.answer(15, [0.5], T0 + 2.0).why == (
        'step 15 is not one published since the samples are fresh (steps 16-19)')
    tick = line.tick(20)
    assert (tick.state, tick.previous, tick.write.tolist()) == (WAITING, WAITING, [0.0])
    assert core.answer(20, [0.25], tick.time + 0.01).resumed


def test_stale_ticks_publish_nothing_write_the_safe_value_and_refuse_answers():
    line = Timeline()
    line.silent = (0.0, math.inf)
    tick = line.tick(0)
    assert (tick.state, tick.y, tick.reason) == (STALE, None, 'no sample on /joint_states yet')
    assert tick.write.tolist() == [0.0] and tick.ages == (math.inf,)
    assert line.core.answer(0, [0.5], T0 + 0.01).why == "the machine's samples are stale"


def test_a_silent_controller_gets_the_safe_value_after_stale_timeout():
    line = Timeline()
    line.tick(0)
    line.core.answer(0, [0.5], T0 + 0.01)
    states = [line.tick(k) for k in range(1, 6)]
    # Answered at T0 + 0.01: silent for more than 0.3 s from the tick at T0 + 0.4 on.
    assert [t.state for t in states] == [FOLLOWING] * 3 + [WAITING] * 2
    assert states[3].reason == 'no input from the controller for 0.390 s'
    assert states[3].previous == FOLLOWING and states[3].write.tolist() == [0.0]
    assert states[4].u_applied.tolist() == [0.0]         # the safe value written at T0 + 0.4
    assert states[4].y is not None                       # the machine still speaks


def test_bad_samples_are_dropped_and_a_clock_offset_is_reported():
    core = BridgeCore(MAPPING)
    kind, why = core.sample(0, JointState(position=[], velocity=[]), 1.0)
    assert kind == DROPPED and 'position[0]: position has 0 item(s)' in why
    kind, why = core.sample(0, joints(1.0, float('nan')), 1.0)
    assert kind == DROPPED and 'not finite' in why
    kind, why = core.sample(0, joints(11.0, 0.5), 1.0)     # stamped 10 s after its arrival
    assert kind == OFFSET and '+10.000 s from its arrival' in why
    assert core.tick(11.0).y.tolist() == [0.5, -0.5]       # taken all the same


def test_a_mapped_topic_the_graph_carries_in_another_type_is_named():
    """Issue 52: a mapping naming the wrong type logged 'no sample yet' and stayed safe."""
    from metampc_plant.bridge_core import type_mismatches
    right = {'/joint_states': ['sensor_msgs/msg/JointState']}
    assert type_mismatches(MAPPING, right, ['std_msgs/msg/Float64MultiArray']) == []
    assert type_mismatches(MAPPING, {}, []) == []      # nothing yet: no sample, no mismatch
    wrong = {'/joint_states': ['sensor_msgs/msg/Imu']}
    assert type_mismatches(MAPPING, wrong, ['std_msgs/msg/Float64MultiArray',
                                            'std_msgs/msg/Float64']) == [
        '/joint_states carries sensor_msgs/msg/Imu, not sensor_msgs/msg/JointState as the '
        'mapping says: no sample of it can come (is the type in the mapping right?)',
        '/effort_controller/commands is read as std_msgs/msg/Float64: the commands go out as '
        'std_msgs/msg/Float64MultiArray, as the mapping says, and reach no reader of another '
        'type (is the type in the mapping right?)']


def test_a_tick_that_fires_late_holds_the_sample_of_t_k_not_of_its_firing_time():
    """Step 1 is due at T0 + 0.1; its timer fires 35 ms late, when a newer sample has come:
    y_1 is still the newest sample stamped at or before t_1."""
    core = BridgeCore(MAPPING)
    core.sample(0, joints(T0 - 0.01, 1.0), T0 - 0.009)
    assert core.tick(T0).y.tolist() == [1.0, -1.0]
    core.sample(0, joints(T0 + 0.09, 2.0), T0 + 0.091)     # before t_1
    core.sample(0, joints(T0 + 0.13, 3.0), T0 + 0.131)     # after t_1, before the firing
    late = core.tick(T0 + 0.135)
    assert late.step == 1 and late.time == pytest.approx(T0 + 0.1, abs=1e-9)
    assert late.y.tolist() == [2.0, -2.0]
    assert late.ages[0] == pytest.approx(0.01, abs=1e-9)


def test_a_sample_exactly_stale_timeout_old_is_fresh():
    """Ages at t_k, in binary-exact times (dt 0.25, stale_timeout 0.5): the sample stamped at
    t_0 is exactly stale_timeout old at t_2 and still fresh (as the offline sampling holds
    it); at t_3 it is stale."""
    mapping = dataclasses.replace(MAPPING, dt=0.25, stale_timeout=0.5)
    core = BridgeCore(mapping)
    core.sample(0, joints(16.0, 1.0), 16.0)
    ticks = [core.tick(16.0 + 0.25 * k) for k in range(4)]
    assert [t.ages[0] for t in ticks] == [0.0, 0.25, 0.5, 0.75]
    assert ticks[2].state != STALE and ticks[2].y.tolist() == [1.0, -1.0]
    assert ticks[3].state == STALE and ticks[3].y is None
