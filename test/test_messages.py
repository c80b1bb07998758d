"""Every metampc message and service type round-trips through CDR with non-default values."""
import array

import pytest
from rclpy.serialization import deserialize_message, serialize_message

import metampc_msgs.msg
import metampc_msgs.srv

MESSAGES = ['PlantOutput', 'PlantInfo', 'ControlInput', 'NssmWeights', 'MpcStatus',
            'TrainingProgress', 'StepHold', 'AdaptRefusal', 'ModelEvent']
SERVICES = ['ResetPlant', 'MetaTrain', 'Adapt', 'SetActive', 'SetBuffering']


def _value(type_name: str, seed: int):
    """A non-default value for a rosidl field type string (e.g. 'sequence<double>')."""
    if type_name.startswith('sequence<'):
        inner = type_name[len('sequence<'):-1]
        return [_value(inner, seed + i) for i in range(3)]
    if type_name == 'boolean':
        return True
    if type_name in ('double', 'float'):
        return 0.5 + seed
    if type_name.startswith(('int', 'uint')) or type_name in ('octet', 'byte'):
        return 1 + seed % 100
    if type_name == 'string':
        return f'text-{seed}'
    if type_name == 'builtin_interfaces/Time':
        from builtin_interfaces.msg import Time
        return Time(sec=12 + seed, nanosec=345)
    if type_name == 'std_msgs/Header':
        from std_msgs.msg import Header
        h = Header(frame_id=f'frame-{seed}')
        h.stamp.sec, h.stamp.nanosec = 12 + seed, 345
        return h
    if type_name.startswith('metampc_msgs/'):     # a message of ours inside another
        return _filled(getattr(metampc_msgs.msg, type_name.split('/')[1]), seed)
    raise AssertionError(f'no test value for field type {type_name}')


def _filled(cls, seed: int = 0):
    msg = cls()
    for i, (name, type_name) in enumerate(cls.get_fields_and_field_types().items()):
        setattr(msg, name, _value(type_name, seed + i))
    return msg


def _plain(value):
    if isinstance(value, (list, tuple, array.array)) or hasattr(value, 'tolist'):
        return [_plain(v) for v in (value.tolist() if hasattr(value, 'tolist') else value)]
    if hasattr(value, 'get_fields_and_field_types'):
        return {k: _plain(getattr(value, k)) for k in value.get_fields_and_field_types()}
    return value


def _types():
    for name in MESSAGES:
        yield name, getattr(metampc_msgs.msg, name)
    for name in SERVICES:
        srv = getattr(metampc_msgs.srv, name)
        yield f'{name}.Request', srv.Request
        yield f'{name}.Response', srv.Response


@pytest.mark.parametrize('name,cls', list(_types()), ids=[n for n, _ in _types()])
def test_cdr_round_trip(name, cls):
    msg = _filled(cls)
    default = cls()
    for field in cls.get_fields_and_field_types():
        assert _plain(getattr(msg, field)) != _plain(getattr(default, field)), field
    back = deserialize_message(serialize_message(msg), cls)
    assert _plain(back) == _plain(msg)


def test_every_field_is_documented():
    """Each field line of every .msg/.srv file carries a comment with its unit or meaning."""
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[1] / 'src' / 'metampc_msgs'
    files = sorted(root.glob('msg/*.msg')) + sorted(root.glob('srv/*.srv'))
    assert len(files) == len(MESSAGES) + len(SERVICES)
    for path in files:
        for line in path.read_text().splitlines():
            code = line.split('#')[0].strip()
            if code and code != '---' and not code.startswith('std_msgs/Header'):
                assert '#' in line, f'{path.name}: undocumented field {code!r}'
