"""message_yaml: every message type of the project and of common_interfaces round-trips through
the YAML that `ros2 topic echo` prints and `ros2 topic pub` reads; the printed text follows
rosidl_runtime_py's format."""
import array
import importlib
import random
import zlib

import numpy as np
import pytest
from rosidl_parser.definition import (AbstractNestedType, AbstractSequence, Array, BasicType,
                                      BoundedSequence, NamespacedType)

from metampc_ros2cli import message_yaml as my

PACKAGES = ('metampc_msgs', 'std_msgs', 'geometry_msgs', 'sensor_msgs', 'nav_msgs',
            'diagnostic_msgs', 'trajectory_msgs', 'visualization_msgs', 'shape_msgs',
            'stereo_msgs', 'actionlib_msgs', 'builtin_interfaces', 'rcl_interfaces',
            'rosgraph_msgs', 'lifecycle_msgs', 'unique_identifier_msgs')
INT_RANGES = {'int8': (-128, 127), 'uint8': (0, 255), 'int16': (-2**15, 2**15 - 1),
              'uint16': (0, 2**16 - 1), 'int32': (-2**31, 2**31 - 1), 'uint32': (0, 2**32 - 1),
              'int64': (-2**63, 2**63 - 1), 'uint64': (0, 2**64 - 1), 'char': (0, 255)}


def message_types():
    out = []
    for package in PACKAGES:
        module = importlib.import_module(f'{package}.msg')
        out += [getattr(module, n) for n in dir(module)
                if n[:1].isupper() and hasattr(getattr(module, n), 'SLOT_TYPES')]
    for package, names in (('metampc_msgs', ('Adapt', 'MetaTrain', 'ResetPlant', 'SetActive',
                                             'SetBuffering')),):
        module = importlib.import_module(f'{package}.srv')
        for n in names:
            out += [getattr(module, n).Request, getattr(module, n).Response]
    return out


def scalar(t, rng):
    """A random value of a basic or string type that the field keeps exactly."""
    if not isinstance(t, BasicType):
        return ''.join(rng.choice('ab c:-{}"\'x\n') for _ in range(rng.randint(0, 6)))
    name = t.typename
    if name == 'boolean':
        return rng.random() < 0.5
    if name == 'octet':
        # Not 0x85: echo prints a byte as its character, as ros2cli does, and YAML reads a
        # NEL character back as a line break (the same with ros2cli).
        return bytes([rng.choice([b for b in range(256) if b != 0x85])])
    if name in INT_RANGES:
        return rng.randint(*INT_RANGES[name])
    x = rng.uniform(-1e3, 1e3)
    return float(np.float32(x)) if name == 'float' else x


def fill(msg, rng, depth=0):
    """Set every field of `msg` to random values (nested messages and sequences included)."""
    for name, t in my.fields(msg).items():
        current = getattr(msg, name)
        if isinstance(t, AbstractNestedType):
            if isinstance(t, Array):
                n = t.size
            else:
                n = rng.randint(0, 3 if depth < 2 else 0)
                if isinstance(t, BoundedSequence):
                    n = min(n, t.maximum_size)
            if isinstance(t.value_type, NamespacedType):
                cls = my.message_class_of(t.value_type)
                items = [cls() for _ in range(n)]
                for item in items:
                    fill(item, rng, depth + 1)
                value = items
            else:
                value = [scalar(t.value_type, rng) for _ in range(n)]
                if isinstance(current, np.ndarray):
                    value = np.array(value, dtype=current.dtype)
                elif isinstance(current, array.array):
                    value = array.array(current.typecode, value)
            setattr(msg, name, value)
        elif isinstance(t, NamespacedType):
            fill(current, rng, depth + 1)
        else:
            setattr(msg, name, scalar(t, rng))
    return msg


TYPES = message_types()


def test_the_types_cover_the_project_and_common_interfaces():
    names = {f'{c.__module__.split(".")[0]}/{c.__name__}' for c in TYPES}
    assert len(TYPES) > 150
    assert {'metampc_msgs/PlantOutput', 'metampc_msgs/NssmWeights', 'sensor_msgs/Image',
            'std_msgs/ByteMultiArray', 'rcl_interfaces/ParameterEvent'} <= names
    assert any(isinstance(t, AbstractSequence) for c in TYPES for t in c.SLOT_TYPES)


@pytest.mark.parametrize('cls', TYPES, ids=lambda c: f'{c.__module__.split(".")[0]}/{c.__name__}')
def test_round_trip_through_the_yaml_echo_prints(cls):
    rng = random.Random(zlib.crc32(cls.__name__.encode()))
    for _ in range(3):
        msg = fill(cls(), rng)
        text = my.to_yaml(msg)
        back = my.from_yaml(cls, text)
        assert back == msg, text
        assert my.from_yaml(cls, my.to_yaml(msg, flow_style=True)) == msg


def test_the_printed_text_is_rosidl_runtime_pys():
    from metampc_msgs.msg import PlantOutput
    from std_msgs.msg import Header
    msg = PlantOutput(step=3, y=[0.5, -1.25])
    msg.header = Header(frame_id='plant')
    msg.header.stamp.sec, msg.header.stamp.nanosec = 2, 50
    text = my.to_yaml(msg)
    assert text.startswith('header:\n  stamp:\n    sec: 2\n    nanosec: 50\n  frame_id: plant\n')
    assert 'y:\n- 0.5\n- -1.25\n' in text
    assert my.to_yaml(msg, flow_style=True).startswith('{header: {stamp: {sec: 2, nanosec: 50}')
    assert "y: '<sequence type: double, length: 2>'" in my.to_yaml(msg, no_arr=True)
    assert "frame_id: '<string length: <5>>'" in my.to_yaml(msg, no_str=True)
    long = PlantOutput(y=list(range(5)))
    assert "y:\n- 0.0\n- 1.0\n- '...'\n" in my.to_yaml(long, truncate_length=2)
    assert my.to_csv(msg) == '2,50,plant,3,0.5,-1.25,,,False,False'  # u_applied, theta empty


@pytest.mark.parametrize('text, reason', [
    ('{step: 1, nope: 2}', "'PlantOutput' object has no attribute 'nope'"),
    ('[1, 2]', 'needs to be a dictionary'),
    ('{step: [1}', 'not valid YAML'),
    ('{step: x}', "step: expected an integer in [0, 18446744073709551615] (uint64), got 'x'"),
    ('{step: -1}', 'step: expected an integer in [0, 18446744073709551615] (uint64), got -1'),
    ('{saturated: 1}', 'saturated: expected true or false, got 1'),
    ('{y: [1, a]}', "y: expected a number (double), got 'a'"),
    ('{header: {frame_id: 3}}', 'header: frame_id: expected a string, got 3'),
    ('{y: 3}', 'y: expected a list'),
])
def test_bad_values_name_the_field(text, reason):
    from metampc_msgs.msg import PlantOutput
    with pytest.raises(ValueError) as err:
        my.from_yaml(PlantOutput, text)
    assert reason in str(err.value)


def test_header_auto_and_time_now_are_left_for_the_publisher_to_stamp():
    from builtin_interfaces.msg import Time
    from metampc_msgs.msg import PlantOutput
    from std_msgs.msg import Header
    stamps = []
    msg = my.from_yaml(PlantOutput, '{header: auto, step: 2}', stamps)
    assert stamps == [(msg.header, 'stamp')] and msg.step == 2
    stamps = []
    header = my.from_yaml(Header, '{stamp: now, frame_id: a}', stamps)
    assert stamps == [(header, 'stamp')] and header.frame_id == 'a'
    for owner, attr in stamps:
        setattr(owner, attr, Time(sec=5))
    assert header.stamp.sec == 5
    with pytest.raises(ValueError, match='header: '):      # without stamps: not a mapping
        my.from_yaml(PlantOutput, '{header: auto}')
