"""The bridge's sampling rule on a recording: a timeline worked out by hand, one skip reason per
sample; and the grid of a simulated robot session against what the bridge's own core gave the
controller live, tick by tick."""
import copy

import numpy as np
import pytest

from metampc_plant.machine_mapping import parse_mapping
from metampc_learner.grid_samples import grid_samples, REASONS
from metampc_learner.recorded_streams import read_bag, Recorded, RecordingError, Stream

pytestmark = pytest.mark.xdist_group('robot_recording')
MAPPING = {'dt': 0.25, 'stale_timeout': 0.6,
           'outputs': [{'name': 'q', 'topic': '/joint_states', 'type':
                        'sensor_msgs/msg/JointState', 'field': 'position[0]', 'max': 2.0},
                       {'name': 'qd', 'topic': '/joint_states', 'type':
                        'sensor_msgs/msg/JointState', 'field': 'velocity[0]'}],
           'command': {'topic': '/cmd', 'type': 'std_msgs/msg/Float64MultiArray', 'inputs': [
               {'field': 'data[0]', 'min': -1.0, 'max': 1.0, 'safe': 0.0}]}}
# Grid t_k = 0.25 k (binary fractions: no rounding). Output samples (stamp, q, qd):
SAMPLES = [(0.0, 0.0, 0.0), (0.25, 0.1, 1.0), (0.5, 0.2, 2.0),      # none at 0.75: a repeat
           (1.0, 0.4, np.nan), (1.25, 0.5, 5.0), (1.5, 2.5, 6.0),   # NaN; q at its max 2
           (1.75, 0.7, 7.0), (2.75, 1.1, 11.0)]                     # silent 2.0-2.5 (stale)
COMMANDS = [(0.125, 0.5), (1.125, 1.2), (1.375, -0.5), (1.75, 0.25)]    # 1.2: beyond max
EXPECTED = ['no_input', '', '', 'repeat', 'nan', 'input_saturated', 'output_saturated', '',
            'repeat', 'repeat', 'stale', '']


def recorded(samples=SAMPLES, commands=COMMANDS):
    s, c = np.array(samples, dtype=float), np.array(commands, dtype=float)
    return Recorded([Stream(s[:, 0], s[:, 1:], (0, 1))], Stream(c[:, 0], c[:, 1:], (0,)),
                    'csv', '', {}, {})


def test_each_rule_on_a_timeline_worked_out_by_hand():
    grid = grid_samples(recorded(), parse_mapping(MAPPING))
    assert grid.times.tolist() == [0.25 * k for k in range(12)]
    assert grid.reasons.tolist() == EXPECTED
    # y_k: the newest sample at or before t_k (0.5 held at 0.75; 1.75 until stale: none)
    np.testing.assert_array_equal(grid.y[:, 0], [0.0, 0.1, 0.2, 0.2, 0.4, 0.5, 2.5, 0.7, 0.7,
                                                 0.7, np.nan, 1.1])
    # u_k: the newest command before t_k; the one stamped t_7 = 1.75 acts from k = 8 on
    assert np.isnan(grid.u[0, 0])
    assert grid.u[1:, 0].tolist() == [0.5] * 4 + [1.2, -0.5, -0.5, 0.25, 0.25, 0.25, 0.25]
    assert grid.counts() == {r: EXPECTED.count(r) for r in REASONS}
    assert grid.skipped_runs() == [(0, 0, 'no_input'), (3, 3, 'repeat'), (4, 4, 'nan'),
                                   (5, 5, 'input_saturated'), (6, 6, 'output_saturated'),
                                   (8, 9, 'repeat'), (10, 10, 'stale')]


def test_kept_saturated_inputs_are_clipped_as_the_bridge_writes_them():
    grid = grid_samples(recorded(), parse_mapping(MAPPING), keep_saturated=True)
    assert grid.reasons[5] == '' and grid.u[5, 0] == 1.0
    assert grid.reasons[6] == 'output_saturated'     # an output's range still holds


def test_the_grid_spans_the_time_every_stream_has_samples():
    two = copy.deepcopy(MAPPING)
    del two['outputs'][0]['max']
    two['outputs'][1]['topic'] = '/other'
    two['outputs'][1]['type'] = 'sensor_msgs/msg/Imu'
    two['outputs'][1]['field'] = 'linear_acceleration.x'
    mapping = parse_mapping(two)
    q = Stream(np.array([0.0, 0.5, 1.0, 1.5, 2.0]), np.arange(5.0)[:, None], (0,))
    x = Stream(np.array([0.5, 1.0, 1.5]), -np.arange(3.0)[:, None], (1,))
    grid = grid_samples(Recorded([q, x], recorded().command, 'bag', '', {}, {}), mapping)
    assert grid.times.tolist() == [0.5, 0.75, 1.0, 1.25, 1.5]
    assert grid.y.tolist() == [[1, 0], [1, 0], [2, -1], [2, -1], [3, -2]]
    assert grid.reasons.tolist() == ['', 'repeat', '', 'repeat', '']
    late = Stream(np.array([5.0]), np.ones((1, 1)), (1,))
    with pytest.raises(RecordingError, match='do not overlap in time'):
        grid_samples(Recorded([q, late], recorded().command, 'bag', '', {}, {}), mapping)


def test_the_offline_samples_are_those_the_bridge_gave_the_controller(robot_session,
                                                                      robot_bag):
    """The session's bag read offline against the bridge core's ticks: every usable sample is
    the live y_k and u_applied_k exactly; the live bridge published no y where the offline
    grid is stale, and clipped where it says input_saturated."""
    from metampc_plant.machine_mapping import load_mapping
    from robot_recording import MAPPING as EXAMPLE
    mapping = load_mapping(EXAMPLE)
    grid = grid_samples(read_bag(str(robot_bag), mapping), mapping)
    ticks = robot_session.ticks
    assert len(grid.times) == len(ticks) and grid.times.tolist() == [t[1] for t in ticks]
    counts = grid.counts()
    assert counts['stale'] >= 3 and counts['nan'] >= 1 and counts['repeat'] >= 1
    assert counts['input_saturated'] >= 5 and counts['no_input'] == 1
    for (k, t, y, u, saturated), reason, y_off, u_off in zip(ticks, grid.reasons, grid.y,
                                                             grid.u):
        assert (y is None) == (reason == 'stale'), k
        if reason == '':
            assert y_off.tolist() == y.tolist() and u_off.tolist() == u.tolist(), k
        if y is not None and reason in ('', 'input_saturated'):
            assert saturated == (reason == 'input_saturated'), k
