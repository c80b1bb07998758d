"""A recording read through the mapping: the robot session's bag in every form rosbags reads
(MCAP and sqlite3 storage, the folder or its one file) against the messages written into it; a
CSV's columns with scale and offset; every bad input one line naming what is wrong."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from metampc_plant.machine_mapping import load_mapping, parse_mapping
from metampc_learner.recorded_streams import (read_bag, read_csv, read_streams,
                                              RecordingError)

pytestmark = pytest.mark.xdist_group('robot_recording')


@pytest.fixture(scope='module')
def mapping():
    from robot_recording import MAPPING
    return load_mapping(MAPPING)


def example_with(**changes):
    """The example mapping file's data with changes: top-level keys, or command__KEY."""
    from robot_recording import MAPPING
    with open(MAPPING) as f:
        data = yaml.safe_load(f)
    for key, value in changes.items():
        section, _, name = key.partition('__')
        (data['command'] if name else data)[name or key] = value
    return parse_mapping(data)


@pytest.mark.parametrize('storage, member', [('mcap', False), ('mcap', True),
                                             ('sqlite3', False), ('sqlite3', True)])
def test_a_bag_gives_the_stamps_and_values_written_into_it(robot_session, tmp_path, mapping,
                                                           storage, member):
    from robot_recording import write_bag
    folder = write_bag(robot_session, tmp_path / 'bag', storage)
    path = next(folder.glob('*.mcap' if storage == 'mcap' else '*.db3')) if member else folder
    got = read_bag(str(path), mapping)
    joints = robot_session.joint_states
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m in joints]
    (states,) = got.outputs
    assert states.columns == (0, 1) and states.stamps.tolist() == stamps
    np.testing.assert_array_equal(states.values, [[m.position[0], m.velocity[0]]
                                                  for _, m in joints])
    commands = robot_session.commands
    assert got.command.stamps.tolist() == [1e-9 * ns for ns, _ in commands]
    assert got.command.values[:, 0].tolist() == [m.data[0] for _, m in commands]
    assert got.read == {'/joint_states': len(joints),
                        '/effort_controller/commands': len(commands)}
    assert got.unreadable == {'/joint_states': 2, '/effort_controller/commands': 0}  # NaN
    assert got.kind == 'bag' and got.clock.startswith('/joint_states: header.stamp')


def test_a_recording_cut_short_gives_the_messages_of_its_complete_chunks(robot_session,
                                                                         tmp_path, mapping):
    """A recorder killed mid-file leaves no summary (rosbags cannot open it): what its
    complete chunks hold is read, a prefix of the finished file's messages as rosbags reads
    them."""
    from robot_recording import write_recording
    whole = write_recording(robot_session, tmp_path / 'whole.mcap', chunk_size=8192)
    data = whole.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:len(data) * 6 // 10])
    full, got = read_bag(str(whole), mapping), read_bag(str(cut), mapping)
    assert full.cut_short == '' and got.cut_short.startswith(f'{cut} was cut short')
    assert all(0 < got.read[k] < full.read[k] for k in full.read)
    for part, all_of in [*zip(got.outputs, full.outputs), (got.command, full.command)]:
        n = len(part.stamps)
        assert part.stamps.tolist() == all_of.stamps[:n].tolist()
        np.testing.assert_array_equal(part.values, all_of.values[:n])    # NaN where NaN
    assert got.unreadable['/effort_controller/commands'] == 0 and got.kind == 'bag'


def test_a_message_too_short_for_the_field_reads_as_nan(tmp_path, mapping):
    from robot_recording import command, joint_state, Session, write_bag
    session = Session(joint_states=[(10**9, joint_state(10**9, [0.5], [1.0])),
                                    (2 * 10**9, joint_state(2 * 10**9, [0.25]))],
                      commands=[(1_500_000_000, command())])
    got = read_bag(str(write_bag(session, tmp_path / 'bag')), mapping)
    np.testing.assert_array_equal(got.outputs[0].values, [[0.5, 1.0], [np.nan, np.nan]])
    assert np.isnan(got.command.values).all()
    assert got.unreadable == {'/joint_states': 1, '/effort_controller/commands': 1}


def test_a_bag_that_does_not_fit_the_mapping_is_one_line(robot_bag, tmp_path, mapping):
    with pytest.raises(RecordingError) as err:
        read_bag(str(robot_bag), example_with(command__topic='/arm/commands'))
    assert str(err.value) == (
        f'command.topic: /arm/commands is not in {robot_bag} (its topics: '
        '/effort_controller/commands (std_msgs/msg/Float64MultiArray), /joint_states '
        '(sensor_msgs/msg/JointState))')
    imu = example_with(outputs=[{'topic': '/joint_states', 'type': 'sensor_msgs/msg/Imu',
                                 'field': 'linear_acceleration.x'}])
    with pytest.raises(RecordingError, match=r'^outputs\[0\].type: /joint_states is '
                       r'sensor_msgs/msg/JointState in .*, not sensor_msgs/msg/Imu$'):
        read_bag(str(robot_bag), imu)
    with pytest.raises(RecordingError, match=r'^.*nowhere: no such file or folder$'):
        read_bag(str(tmp_path / 'nowhere'), mapping)
    (tmp_path / 'notes.txt').write_text('no bag')
    with pytest.raises(RecordingError) as err:
        read_bag(str(tmp_path / 'notes.txt'), mapping)
    assert str(err.value) == (f"{tmp_path / 'notes.txt'}: not a readable bag (Unrecognized "
                              "storage format '.txt')")


def test_a_bag_whose_type_lacks_a_mapped_field_is_one_line(tmp_path, mapping):
    """The bag's own definition of the type (not the installed one) has no velocity."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    jazzy, store = get_typestore(Stores.ROS2_JAZZY), get_typestore(Stores.EMPTY)
    types = {n: jazzy.fielddefs[n] for n in ('builtin_interfaces/msg/Time',
                                             'std_msgs/msg/Header',
                                             'std_msgs/msg/MultiArrayDimension',
                                             'std_msgs/msg/MultiArrayLayout',
                                             'std_msgs/msg/Float64MultiArray')}
    types.update(get_types_from_msg('std_msgs/Header header\nfloat64[] position\n',
                                    'sensor_msgs/msg/JointState'))
    store.register(types)
    t = store.types
    msg = t['sensor_msgs/msg/JointState'](header=t['std_msgs/msg/Header'](
        stamp=t['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id=''),
        position=np.array([0.5]))
    with Writer(tmp_path / 'old', version=9) as writer:
        joints = writer.add_connection('/joint_states', 'sensor_msgs/msg/JointState',
                                       typestore=store)
        writer.add_connection('/effort_controller/commands', 'std_msgs/msg/Float64MultiArray',
                              typestore=store)
        writer.write(joints, 1, store.serialize_cdr(msg, 'sensor_msgs/msg/JointState'))
    with pytest.raises(RecordingError) as err:
        read_bag(str(tmp_path / 'old'), mapping)
    assert str(err.value) == (f"outputs[0]: the messages of /joint_states in {tmp_path / 'old'} "
                              "have no field 'velocity' (its type there differs from the "
                              'installed one)')


def write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_csv_columns_are_the_fields_with_scale_and_offset(tmp_path):
    scaled = example_with(outputs=[
        {'name': 'q', 'topic': '/joint_states', 'type': 'sensor_msgs/msg/JointState',
         'field': 'position[0]', 'scale': 2.0, 'offset': 1.0},
        {'name': 'qd', 'topic': '/joint_states', 'type': 'sensor_msgs/msg/JointState',
         'field': 'velocity[0]'}], command__inputs=[
        {'name': 'tau', 'field': 'data[0]', 'scale': -4.0, 'offset': 0.5, 'min': -1.0,
         'max': 1.0, 'safe': 0.0}])
    path = write(tmp_path / 'log.csv', 'tau,qd,time,q\n2.5,0.5,10.0,1\n-1.5,,10.5,2\n')
    got = read_streams(path, scaled)
    (y,) = got.outputs
    assert y.stamps.tolist() == [10.0, 10.5] and got.command.stamps.tolist() == [10.0, 10.5]
    np.testing.assert_array_equal(y.values, [[3.0, 0.5], [5.0, np.nan]])
    assert got.command.values[:, 0].tolist() == [-0.5, 0.5]
    assert got.unreadable == {'outputs': 1, 'inputs': 0} and got.clock == "column 'time', s"


def test_csv_rows_without_a_time_column_are_dt_apart_or_the_named_column_is_the_time(
        tmp_path, mapping):
    path = write(tmp_path / 'log.csv', 'q,qd,tau,t\n1,2,3,7\n4,5,6,8\n7,8,9,9.5\n')
    rows = read_csv(path, mapping)
    assert rows.outputs[0].stamps.tolist() == [0.0, 0.1, 0.2]
    assert rows.clock == 'one row per dt = 0.1 s'
    named = read_csv(path, mapping, time_column='t')
    assert named.outputs[0].stamps.tolist() == [7.0, 8.0, 9.5]
    assert named.outputs[0].values.tolist() == [[1, 2], [4, 5], [7, 8]]


@pytest.mark.parametrize('text, options, message', [
    ('q,tau,time\n1,2,3\n', {}, "no column 'qd' (outputs[1].name; its columns: q, tau, time)"),
    ('q,qd,tau\n1,2,3\n', {'time_column': 'stamp'},
     "no column 'stamp' (the time column; its columns: q, qd, tau)"),
    ('q,qd,tau,time\n1,2,3,0\n1,x2,3,1\n', {}, "row 3, column 'qd': 'x2' is no number"),
    ('q,qd,tau,time\n1,2,3,1\n1,2,3,1\n', {}, 'row 3: the time 1.0 is not after the row '
     'before (1.0)'),
    # Issue 52: both said 'is not finite and after the row before', the time cut to 6 digits.
    ('q,qd,tau,time\n1,2,3,1796670000.5\n1,2,3,1796670000.25\n', {},
     'row 3: the time 1796670000.25 is not after the row before (1796670000.5)'),
    ('q,qd,tau,time\n1,2,3,0\n\n1,2,3,inf\n', {}, 'row 4: the time inf is not finite'),
    # Issue 52: a short row was read as empty cells.
    ('q,qd,tau,time\n1,2,3,0\n1,2\n', {}, 'row 3 has 2 cell(s), the header 4'),
    ('', {}, 'empty (a header row of column names is needed)'),
])
def test_a_csv_that_does_not_fit_is_one_line(tmp_path, mapping, text, options, message):
    path = write(tmp_path / 'log.csv', text)
    with pytest.raises(RecordingError) as err:
        read_csv(path, mapping, **options)
    assert str(err.value) == f'{path}: {message}'


def test_a_missing_csv_or_a_time_column_for_a_bag_is_one_line(tmp_path, robot_bag, mapping):
    with pytest.raises(RecordingError, match=r'^cannot read .*gone.csv: No such file'):
        read_streams(str(tmp_path / 'gone.csv'), mapping)
    with pytest.raises(RecordingError, match='a time column is for a CSV, not a bag'):
        read_streams(str(robot_bag), mapping, time_column='t')
