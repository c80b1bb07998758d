"""The mapping file: values read from and written into real message types (rclpy's generated
classes and rosbags' decoded ones), against values worked out by hand; every wrong mapping is
one line naming its key."""
import copy
import os

from geometry_msgs.msg import Point32, Polygon, PoseStamped, Twist
from metampc_plant.machine_mapping import load_mapping, MappingError, parse_mapping
import numpy as np
import pytest
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(
    __file__)))))
EXAMPLE = os.path.join(ROOT, 'examples', 'joint_robot', 'mapping.yaml')
JOINTS = 'sensor_msgs/msg/JointState'
BASE = {'dt': 0.1, 'stale_timeout': 0.3,
        'outputs': [{'topic': '/joint_states', 'type': JOINTS, 'field': 'position[0]'}],
        'command': {'topic': '/cmd', 'type': 'std_msgs/msg/Float64MultiArray',
                    'inputs': [{'field': 'data[0]', 'min': -1.0, 'max': 1.0, 'safe': 0.0}]}}


def mapping_with(**changes):
    """BASE with changes: top-level keys, or 'output'/'input'/'command' for their dicts."""
    data = copy.deepcopy(BASE)
    data['outputs'][0].update(changes.pop('output', {}))
    data['command']['inputs'][0].update(changes.pop('input', {}))
    data['command'].update(changes.pop('command', {}))
    data.update(changes)
    return data


def joints(stamp_s: int, position, velocity=()):
    msg = JointState(name=['j1'] * len(position), position=list(position),
                     velocity=list(velocity))
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_s, 250_000_000
    return msg


def test_the_example_file_maps_joint_states_to_y_and_u_to_a_float64_multi_array():
    m = load_mapping(EXAMPLE)
    assert (m.name, m.dt, m.stale_timeout) == ('joint_robot', 0.1, 0.3)
    assert [(o.name, o.unit, o.topic) for o in m.outputs] == [
        ('q', 'rad', '/joint_states'), ('qd', 'rad/s', '/joint_states')]
    (topic,) = m.topics         # one subscription gives both outputs, stamped by its header
    assert (topic.type, topic.outputs, topic.stamp.text) == (JOINTS, (0, 1), 'header.stamp')
    msg = joints(7, [0.25], [-1.5])
    assert m.output_values(topic, msg).tolist() == [0.25, -1.5]
    assert m.stamp(topic, msg, received=99.0) == 7.25
    assert (m.u_min.tolist(), m.u_max.tolist(), m.safe.tolist()) == ([-1.0], [1.0], [0.0])
    assert (m.y_min.tolist(), m.y_max.tolist()) == ([-np.inf] * 2, [np.inf] * 2)
    command = m.command_message([0.75])
    assert isinstance(command, Float64MultiArray) and list(command.data) == [0.75]
    assert m.command_values(command).tolist() == [0.75]


def test_scale_and_offset_apply_both_ways():
    """y = scale * field + offset; the command field = scale * u + offset, and back."""
    data = mapping_with(output={'scale': 2.0, 'offset': 1.0},
                        input={'scale': -4.0, 'offset': 0.5})
    data['command']['inputs'].append({'field': 'data[2]', 'min': 0, 'max': 2, 'safe': 1})
    m = parse_mapping(data)
    assert m.output_values(m.topics[0], joints(0, [0.25])).tolist() == [1.5]
    msg = m.command_message([0.5, 1.5])
    assert list(msg.data) == [-1.5, 0.0, 1.5]       # data[1] grown with 0.0
    assert m.command_values(msg).tolist() == [0.5, 1.5]


def test_an_output_range_needs_only_the_side_that_is_stated():
    assert parse_mapping(mapping_with(output={'max': 10})).y_max.tolist() == [10.0]
    low = parse_mapping(mapping_with(output={'min': -0.5}))
    assert (low.y_min.tolist(), low.y_max.tolist()) == ([-0.5], [np.inf])


def test_nested_fields_fixed_arrays_sequences_of_messages_and_the_receive_stamp():
    data = mapping_with(outputs=[
        {'name': 'x', 'topic': '/pose', 'type': 'geometry_msgs/msg/PoseStamped',
         'field': 'pose.position.x'},
        {'name': 'var', 'topic': '/imu', 'type': 'sensor_msgs/msg/Imu',
         'field': 'orientation_covariance[8]', 'stamp': 'receive'},
        {'name': 'y1', 'topic': '/area', 'type': 'geometry_msgs/msg/Polygon',
         'field': 'points[1].y'}])
    m = parse_mapping(data)
    pose, imu, area = m.topics
    msg = PoseStamped()
    msg.pose.position.x, msg.header.stamp.sec = 3.5, 2
    assert (m.output_values(pose, msg).tolist(), m.stamp(pose, msg, 9.0)) == ([3.5], 2.0)
    msg = Imu()
    msg.orientation_covariance[8] = 0.125
    msg.header.stamp.sec = 2
    assert (m.output_values(imu, msg).tolist(), m.stamp(imu, msg, 9.0)) == ([0.125], 9.0)
    msg = Polygon(points=[Point32(), Point32(y=-2.0)])        # no header: the receive time
    assert (m.output_values(area, msg).tolist(), m.stamp(area, msg, 9.0)) == ([-2.0], 9.0)
    assert area.stamp is None
    with pytest.raises(ValueError, match=r'points\[1\].y: points has 1 item'):
        m.output_values(area, Polygon(points=[Point32()]))


def test_a_custom_command_type_a_fixed_field_and_its_header_stamp():
    from builtin_interfaces.msg import Time
    twist = parse_mapping(mapping_with(command={'type': 'geometry_msgs/msg/Twist', 'inputs': [
        {'field': 'linear.x', 'min': -1, 'max': 1, 'safe': 0},
        {'field': 'angular.z', 'scale': 0.5, 'min': -2, 'max': 2, 'safe': 0}]}))
    msg = twist.command_message([0.5, -2.0], Time(sec=3))
    assert isinstance(msg, Twist) and (msg.linear.x, msg.angular.z) == (0.5, -1.0)
    effort = parse_mapping(mapping_with(command={
        'type': JOINTS, 'fixed': {'name': ['a', 'b'], 'header.frame_id': 'base'},
        'inputs': [{'field': 'effort[1]', 'min': -1, 'max': 1, 'safe': 0}]}))
    msg = effort.command_message([0.25], Time(sec=3, nanosec=5))
    assert (msg.name, msg.header.frame_id, list(msg.effort)) == (['a', 'b'], 'base', [0, 0.25])
    assert msg.header.stamp == Time(sec=3, nanosec=5)
    area = parse_mapping(mapping_with(command={'type': 'geometry_msgs/msg/Polygon', 'inputs': [
        {'field': 'points[2].x', 'min': -1, 'max': 1, 'safe': 0}]}))
    msg = area.command_message([0.5])         # grown with Point32 messages
    assert [p.x for p in msg.points] == [0.0, 0.0, 0.5]


def test_a_message_decoded_by_rosbags_reads_as_the_live_one():
    """What an offline tool gets from a recording: rosbags' own message classes."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    stamp = types['builtin_interfaces/msg/Time'](sec=7, nanosec=250_000_000)
    msg = types[JOINTS](header=types['std_msgs/msg/Header'](stamp=stamp, frame_id=''),
                        name=['j1'], position=np.array([0.25]), velocity=np.array([-1.5]),
                        effort=np.array([0.0]))
    decoded = store.deserialize_cdr(store.serialize_cdr(msg, JOINTS), JOINTS)
    m = load_mapping(EXAMPLE)
    assert m.output_values(m.topics[0], decoded).tolist() == [0.25, -1.5]
    assert m.stamp(m.topics[0], decoded, received=0.0) == 7.25
    command = types['std_msgs/msg/Float64MultiArray'](
        layout=types['std_msgs/msg/MultiArrayLayout'](dim=[], data_offset=0),
        data=np.array([0.75]))
    assert m.command_values(command).tolist() == [0.75]


BAD = [
    (mapping_with(output={'field': 'positon[0]'}), "outputs[0].field: sensor_msgs/msg/JointState "
     "has no field 'positon' (its fields: header, name, position, velocity, effort)"),
    (mapping_with(output={'type': 'sensor_msgs/msg/JointStat'}),
     "outputs[0].type: unknown message type 'sensor_msgs/msg/JointStat'"),
    (mapping_with(output={'type': 'JointState'}),
     "outputs[0].type: 'JointState' is no message type name"),
    (mapping_with(output={'field': 'name[0]'}),
     'outputs[0].field: name[0] of sensor_msgs/msg/JointState is string, not a number'),
    (mapping_with(output={'field': 'header'}), 'outputs[0].field: header of '
     'sensor_msgs/msg/JointState is std_msgs/msg/Header, not a number'),
    (mapping_with(output={'field': 'position'}), 'outputs[0].field: position of '
     'sensor_msgs/msg/JointState is sequence<double>: give an index, e.g. position[0]'),
    (mapping_with(output={'field': 'header[0]'}),
     'outputs[0].field: header of sensor_msgs/msg/JointState is std_msgs/msg/Header, not an '
     'array'),
    (mapping_with(output={'type': 'sensor_msgs/msg/Imu', 'field': 'orientation_covariance[9]'}),
     'outputs[0].field: orientation_covariance of sensor_msgs/msg/Imu is double[9]: index 9 '
     'is beyond it'),
    (mapping_with(output={'field': 'position[0].x'}), "outputs[0].field: position[0] of "
     "sensor_msgs/msg/JointState is double: it has no field 'x'"),
    (mapping_with(output={'field': 'position[-1]'}), "outputs[0].field: 'position[-1]' is no "
     'field path'),
    (mapping_with(output={'stamp': 'position[0]'}), 'outputs[0].stamp: position[0] of '
     'sensor_msgs/msg/JointState is double, not a builtin_interfaces/msg/Time (or receive)'),
    (mapping_with(output={'scael': 2.0}), 'outputs[0].scael: unknown key (expected one of '),
    (mapping_with(output={'scale': 0}), 'outputs[0].scale must be a finite number other than 0'),
    (mapping_with(output={'min': 2, 'max': 1}), 'outputs[0]: min 2 must be below max 1'),
    (mapping_with(output={'max': '.inf'}), "outputs[0].max must be a number, got '.inf'"),
    (mapping_with(output={'topic': 'joint states'}),
     "outputs[0].topic: 'joint states' is no topic name"),
    (mapping_with(outputs=[]), 'outputs: expected a non-empty list'),
    (mapping_with(outputs=[BASE['outputs'][0], {'topic': '/joint_states', 'type':
                                                'sensor_msgs/msg/Imu',
                                                'field': 'linear_acceleration.x'}]),
     'outputs[1].type: /joint_states is sensor_msgs/msg/JointState in an earlier output'),
    (mapping_with(outputs=[dict(BASE['outputs'][0], name='q')] * 2),
     "outputs[1].name: 'q' is named twice"),
    (mapping_with(dt='fast'), "dt must be a number, got 'fast'"),
    (mapping_with(stale_timeout=0.1), 'stale_timeout: 0.1 s must exceed dt = 0.1 s'),
    (dict(BASE, command={'topic': '/cmd', 'inputs': []}), 'command.type: missing'),
    (mapping_with(input={'min': 1.0}), 'command.inputs[0]: min 1 must be below max 1'),
    (mapping_with(input={'safe': 2.0}),
     'command.inputs[0].safe: 2 is outside [min, max] = [-1, 1]'),
    (mapping_with(input={'field': None}), 'command.inputs[0].field: expected a field path'),
    (mapping_with(command={'type': 'std_msgs/msg/Int32MultiArray'}), 'command.inputs[0].field: '
     'data[0] of std_msgs/msg/Int32MultiArray is int32, not a float32 or float64'),
    (mapping_with(command={'type': JOINTS, 'fixed': {'name': 3},
                           'inputs': [{'field': 'effort[0]', 'min': 0, 'max': 1, 'safe': 0}]}),
     'command.fixed.name: 3 does not fit its type sequence<string>'),
    (mapping_with(command={'type': JOINTS, 'fixed': {'header.frame_id': 1.5},
                           'inputs': [{'field': 'effort[0]', 'min': 0, 'max': 1, 'safe': 0}]}),
     'command.fixed.header.frame_id: 1.5 does not fit its type string'),
    ([1, 2], 'the file: expected a mapping'),
]


@pytest.mark.parametrize('data, message', BAD, ids=[m.split(':')[0] + str(i)
                                                    for i, (_, m) in enumerate(BAD)])
def test_a_wrong_mapping_is_one_line_that_names_the_key(data, message):
    with pytest.raises(MappingError) as err:
        parse_mapping(data)
    assert str(err.value).startswith(message), str(err.value)
    assert '\n' not in str(err.value)


def test_an_unreadable_file_or_bad_yaml_is_one_line(tmp_path):
    with pytest.raises(MappingError, match=r'^cannot read .*nowhere.yaml: No such file'):
        load_mapping(str(tmp_path / 'nowhere.yaml'))
    bad = tmp_path / 'bad.yaml'
    bad.write_text('dt: [0.1\noutputs: 3\n')
    with pytest.raises(MappingError) as err:
        load_mapping(str(bad))
    assert str(err.value).startswith(f'{bad} is no YAML: ') and '\n' not in str(err.value)
    good = tmp_path / 'good.yaml'
    good.write_text(yaml.safe_dump(BASE))
    assert load_mapping(str(good)).outputs[0].field.text == 'position[0]'
