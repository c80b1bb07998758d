"""One machine's topics as the controller's y and u: the mapping file, checked, and its accessors.

A YAML file names each output y_i (a topic, its message type, a field path such as
``position[0]`` or ``pose.position.x``, scale and offset: y_i = scale * field + offset) and the
command (a topic and type; per input a field, scale, offset, bounds and safe value: field =
scale * u_j + offset), the controller's dt and the stale timeout. :func:`load_mapping` checks it
against the types' rosidl introspection (``SLOT_TYPES`` of the generated classes) and raises one
:class:`MappingError` line naming the key. No rclpy: the accessors read any object that has the
fields as attributes (rosbags' and mcap_ros2's decoded messages too), so an offline tool reads a
recording with the same file. Format: docs/bridge.md.
"""
from dataclasses import dataclass
import math
import re
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

from metampc_common.message_types import message_class
from metampc_common.params import number, ParameterError
import numpy as np
from rosidl_parser.definition import (AbstractNestedType, AbstractString, AbstractWString, Array,
                                      BasicType, BoundedSequence, FLOATING_POINT_TYPES,
                                      INTEGER_TYPES, NamespacedType)
import yaml

RECEIVE = 'receive'     # the stamp rule of a topic whose samples are stamped on arrival
TIME_TYPE = 'builtin_interfaces/msg/Time'
_NUMERIC = frozenset(FLOATING_POINT_TYPES) | frozenset(INTEGER_TYPES) | {'boolean'}
_FLOATS = frozenset(FLOATING_POINT_TYPES)
_STEP = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)(?:\[(\d+)\])?$')
_TOPIC = re.compile(r'^(~/|/)?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')
KEYS = {'': ('name', 'dt', 'stale_timeout', 'outputs', 'command'),
        'output': ('name', 'unit', 'topic', 'type', 'field', 'scale', 'offset', 'stamp', 'min',
                   'max'),
        'command': ('topic', 'type', 'inputs', 'fixed'),
        'input': ('name', 'unit', 'field', 'scale', 'offset', 'min', 'max', 'safe')}


class MappingError(ValueError):
    """The mapping file is unreadable or wrong; the text is one line that names the key."""


class Step(NamedTuple):
    """One step of a field path: a field `name`, an optional `index` into it, and `blank`,
    what grows a sequence up to the index when a message is written (float, int, str, bool or
    a nested message class, called without arguments)."""

    name: str
    index: Optional[int]
    blank: Callable[[], Any]


@dataclass(frozen=True)
class FieldPath:
    """A checked path into a message type: ``text`` as written, its steps, and ``leaf``, the
    rosidl type of what it reaches ('double', 'string', 'builtin_interfaces/msg/Time', ...)."""

    text: str
    steps: Tuple[Step, ...]
    leaf: str

    def get(self, msg: Any) -> Any:
        """The value at the path in `msg`; ValueError if a sequence is too short."""
        value = msg
        for step in self.steps:
            value = getattr(value, step.name)
            if step.index is not None:
                if step.index >= len(value):
                    raise ValueError(f'{self.text}: {step.name} has {len(value)} item(s)')
                value = value[step.index]
        return value

    def set(self, msg: Any, value: Any) -> None:
        """Write `value` at the path in `msg`, growing sequences up to the indices."""
        *inner, last = self.steps
        obj = msg
        for step in inner:
            obj = getattr(obj, step.name)
            if step.index is not None:
                obj = _grown(obj, step)[step.index]
        if last.index is None:
            setattr(obj, last.name, value)
        else:
            _grown(getattr(obj, last.name), last)[last.index] = value


def _grown(sequence: Any, step: Step) -> Any:
    """`sequence` (a message's list, array or fixed numpy array) with at least index + 1
    items, grown in place."""
    while len(sequence) <= step.index:
        sequence.append(step.blank())
    return sequence


def _slot_name(slot: Any) -> str:
    """A rosidl type as the mapping's messages name it."""
    if isinstance(slot, NamespacedType):
        return '/'.join(slot.namespaced_name())
    if isinstance(slot, AbstractNestedType):
        inner = _slot_name(slot.value_type)
        if isinstance(slot, Array):
            return f'{inner}[{slot.size}]'
        bound = f'<={slot.maximum_size}' if isinstance(slot, BoundedSequence) else ''
        return f'sequence<{inner}{bound}>'
    if isinstance(slot, (AbstractString, AbstractWString)):
        return 'string'
    return slot.typename if isinstance(slot, BasicType) else type(slot).__name__


def _blank(slot: Any) -> Callable[[], Any]:
    """What grows a sequence of `slot` items."""
    if isinstance(slot, NamespacedType):
        return message_class('/'.join(slot.namespaced_name()))
    if isinstance(slot, (AbstractString, AbstractWString)):
        return str
    name = getattr(slot, 'typename', '')
    return float if name in _FLOATS else bool if name == 'boolean' else int


def resolve_path(type_name: str, text: Any, key: str, whole: bool = False) -> FieldPath:
    """`text` ('a.b[2].c') checked against the fields of message type `type_name`; `whole`:
    the path may end at an array (a whole array set at once), else every array is indexed.

    Raises:
        MappingError: a malformed path, a field the type does not have, an index into a field
            that is no array or beyond a fixed or bounded size, or an array without an index.
    """
    if not isinstance(text, str) or not text:
        raise MappingError(f'{key}: expected a field path such as position[0], got {text!r}')
    parts = [_STEP.match(p) for p in text.split('.')]
    if not all(parts):
        raise MappingError(f'{key}: {text!r} is no field path (names joined by dots, each '
                           'with an optional [index], e.g. pose.position.x or position[0])')
    owner, cls = type_name, _message_class(type_name, key)
    steps, leaf = [], None
    for i, match in enumerate(parts):
        name, index = match.group(1), match.group(2)
        if cls is None:
            raise MappingError(f'{key}: {".".join(p.group(0) for p in parts[:i])} of '
                               f'{type_name} is {leaf}: it has no field {name!r}')
        slots = dict(zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES))
        if name not in slots:
            raise MappingError(f'{key}: {owner} has no field {name!r} (its fields: '
                               f'{", ".join(slots)})')
        slot = slots[name]
        whole_array = whole and index is None and i == len(parts) - 1
        if isinstance(slot, AbstractNestedType) and not whole_array:
            if index is None:
                raise MappingError(f'{key}: {name} of {owner} is {_slot_name(slot)}: give an '
                                   f'index, e.g. {name}[0]')
            limit = (slot.size if isinstance(slot, Array) else
                     slot.maximum_size if isinstance(slot, BoundedSequence) else None)
            if limit is not None and int(index) >= limit:
                raise MappingError(f'{key}: {name} of {owner} is {_slot_name(slot)}: index '
                                   f'{index} is beyond it')
            slot = slot.value_type
        elif index is not None:
            raise MappingError(f'{key}: {name} of {owner} is {_slot_name(slot)}, not an array')
        steps.append(Step(name, None if index is None else int(index), _blank(slot)))
        leaf = _slot_name(slot)
        cls, owner = (message_class(leaf), leaf) if isinstance(slot, NamespacedType) else (
            None, owner)
    return FieldPath(text, tuple(steps), leaf)


def _message_class(type_name: Any, key: str) -> type:
    """The class of a mapping's message type; MappingError naming `key` if there is none."""
    try:
        return message_class(type_name)
    except (ValueError, TypeError):
        raise MappingError(f'{key}: {type_name!r} is no message type name (pkg/msg/Type)') \
            from None
    except (ImportError, AttributeError):
        raise MappingError(f'{key}: unknown message type {type_name!r} (not installed, or its '
                           'workspace not sourced)') from None


def _checked_leaf(path: FieldPath, type_name: str, kinds: frozenset, key: str, want: str
                  ) -> FieldPath:
    if path.leaf not in kinds:
        raise MappingError(f'{key}: {path.text} of {type_name} is {path.leaf}, not {want}')
    return path


@dataclass(frozen=True)
class Output:
    """Output y_i = scale * (field of the topic's message) + offset; [min, max]: the range the
    sensor reads (-inf, inf unless stated): a y_i at or beyond it is saturated."""

    name: str
    unit: str
    topic: str
    type: str
    field: FieldPath
    scale: float
    offset: float
    min: float = -math.inf
    max: float = math.inf


@dataclass(frozen=True)
class Input:
    """Input u_j, in [min, max]; written as field = scale * u_j + offset; ``safe`` is the u_j
    written while the machine or the controller is silent."""

    name: str
    unit: str
    field: FieldPath
    scale: float
    offset: float
    min: float
    max: float
    safe: float


@dataclass(frozen=True)
class Topic:
    """One subscribed topic: its type and class, the rule of its samples' stamps (a path to a
    builtin_interfaces/msg/Time, or None: the receive time) and which outputs it gives."""

    topic: str
    type: str
    cls: type
    stamp: Optional[FieldPath]
    outputs: Tuple[int, ...]


@dataclass(frozen=True)
class Command:
    """The machine's command topic: its type and class, the inputs, and fields written with
    a constant in every message (``fixed``: (path, value) pairs)."""

    topic: str
    type: str
    cls: type
    inputs: Tuple[Input, ...]
    fixed: Tuple[Tuple[FieldPath, Any], ...]


@dataclass(frozen=True)
class MachineMapping:
    """A checked mapping file (see the module docstring); dt and stale_timeout in s."""

    name: str
    dt: float
    stale_timeout: float
    outputs: Tuple[Output, ...]
    topics: Tuple[Topic, ...]
    command: Command

    @property
    def u_min(self) -> np.ndarray:
        return np.array([i.min for i in self.command.inputs])

    @property
    def u_max(self) -> np.ndarray:
        return np.array([i.max for i in self.command.inputs])

    @property
    def safe(self) -> np.ndarray:
        return np.array([i.safe for i in self.command.inputs])

    @property
    def y_min(self) -> np.ndarray:
        return np.array([o.min for o in self.outputs])

    @property
    def y_max(self) -> np.ndarray:
        return np.array([o.max for o in self.outputs])

    def stamp(self, topic: Topic, msg: Any, received: float) -> float:
        """A sample's time, s: its stamp field (sec + 1e-9 nanosec), or `received`."""
        if topic.stamp is None:
            return received
        t = topic.stamp.get(msg)
        return t.sec + 1e-9 * t.nanosec

    def output_values(self, topic: Topic, msg: Any) -> np.ndarray:
        """The outputs `topic` gives (its ``outputs``, in order) from one of its messages;
        ValueError if a sequence is too short."""
        return np.array([self.outputs[i].scale * float(self.outputs[i].field.get(msg))
                         + self.outputs[i].offset for i in topic.outputs])

    def command_message(self, u: Sequence[float], stamp: Optional[Any] = None) -> Any:
        """The command message writing input `u` (n_u values); `stamp` (a
        builtin_interfaces/msg/Time) goes into a top-level std_msgs Header if there is one."""
        command = self.command
        msg = command.cls()
        for path, value in command.fixed:
            path.set(msg, value)
        for item, value in zip(command.inputs, u):
            item.field.set(msg, item.scale * float(value) + item.offset)
        if stamp is not None and 'header' in command.cls.get_fields_and_field_types():
            msg.header.stamp = stamp
        return msg

    def command_values(self, msg: Any) -> np.ndarray:
        """The input u a command message writes (the inverse of :meth:`command_message`), e.g.
        to read a recorded command topic; ValueError if a sequence is too short."""
        return np.array([(float(item.field.get(msg)) - item.offset) / item.scale
                         for item in self.command.inputs])


def load_mapping(path: str) -> MachineMapping:
    """The mapping in YAML file `path`, checked (:func:`parse_mapping`).

    Raises:
        MappingError: an unreadable file, bad YAML, or a bad mapping (one line).
    """
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except OSError as err:
        raise MappingError(f'cannot read {path}: {err.strerror}') from None
    except yaml.YAMLError as err:
        raise MappingError(f'{path} is no YAML: {" ".join(str(err).split())}') from None
    return parse_mapping(data)


def _mapping(value: Any, key: str, kind: str, required: Sequence[str]) -> Dict[str, Any]:
    """`value` as a mapping with only the keys of `kind` and all of `required`."""
    if not isinstance(value, dict):
        raise MappingError(f'{key or "the file"}: expected a mapping, got {value!r}')
    for name in value:
        if name not in KEYS[kind]:
            raise MappingError(f'{_join(key, str(name))}: unknown key (expected one of '
                               f'{", ".join(KEYS[kind])})')
    for name in required:
        if name not in value:
            raise MappingError(f'{_join(key, name)}: missing')
    return value


def _join(key: str, name: str) -> str:
    return f'{key}.{name}' if key else name


def _list(value: Any, key: str) -> List[Any]:
    if not isinstance(value, list) or not value:
        raise MappingError(f'{key}: expected a non-empty list, got {value!r}')
    return value


def _number(data: Mapping[str, Any], name: str, key: str, default: Optional[float] = None,
            positive: bool = False, nonzero: bool = False) -> float:
    full = _join(key, name)
    try:
        x = number(full, data.get(name, default))
    except ParameterError as err:
        raise MappingError(str(err)) from None
    if not math.isfinite(x) or (positive and x <= 0) or (nonzero and x == 0):
        want = 'a finite number' + (' > 0' if positive else ' other than 0' if nonzero else '')
        raise MappingError(f'{full} must be {want}, got {x}')
    return x


def _text(data: Mapping[str, Any], name: str, key: str, default: str) -> str:
    value = data.get(name, default)
    if not isinstance(value, str):
        raise MappingError(f'{_join(key, name)}: expected a string, got {value!r}')
    return value


def _topic(data: Mapping[str, Any], key: str) -> str:
    value = data['topic']
    if not isinstance(value, str) or not _TOPIC.match(value):
        raise MappingError(f'{key}.topic: {value!r} is no topic name')
    return value


def _unique(names: Sequence[str], key: str) -> None:
    for i, name in enumerate(names):
        if name in names[:i]:
            raise MappingError(f'{key}[{i}].name: {name!r} is named twice')


def _stamp_rule(cls: type, type_name: str, data: Mapping[str, Any], key: str
                ) -> Optional[FieldPath]:
    """A topic's stamp: the `stamp` key (a Time field's path, or 'receive'); by default its
    top-level std_msgs Header's stamp, else the receive time."""
    if 'stamp' in data:
        if data['stamp'] == RECEIVE:
            return None
        path = resolve_path(type_name, data['stamp'], f'{key}.stamp')
        return _checked_leaf(path, type_name, frozenset({TIME_TYPE}), f'{key}.stamp',
                             f'a {TIME_TYPE} (or {RECEIVE})')
    fields = cls.get_fields_and_field_types()
    if fields.get('header') == 'std_msgs/Header':
        return resolve_path(type_name, 'header.stamp', key)
    return None


def _outputs(items: List[Any]) -> Tuple[Tuple[Output, ...], Tuple[Topic, ...]]:
    outputs: List[Output] = []
    topics: Dict[str, Topic] = {}
    for i, raw in enumerate(items):
        key = f'outputs[{i}]'
        data = _mapping(raw, key, 'output', ('topic', 'type', 'field'))
        topic, type_name = _topic(data, key), data['type']
        cls = _message_class(type_name, f'{key}.type')
        path = _checked_leaf(resolve_path(type_name, data['field'], f'{key}.field'), type_name,
                             _NUMERIC, f'{key}.field', 'a number')
        stamp = _stamp_rule(cls, type_name, data, key)
        known = topics.get(topic)
        if known is not None:
            if known.type != type_name:
                raise MappingError(f'{key}.type: {topic} is {known.type} in an earlier output, '
                                   f'not {type_name}')
            if (known.stamp and known.stamp.text) != (stamp and stamp.text):
                raise MappingError(f'{key}.stamp: {topic} is stamped by '
                                   f'{known.stamp.text if known.stamp else RECEIVE} in an '
                                   'earlier output')
        low = _number(data, 'min', key) if 'min' in data else -math.inf
        high = _number(data, 'max', key) if 'max' in data else math.inf
        if not low < high:
            raise MappingError(f'{key}: min {low:g} must be below max {high:g}')
        outputs.append(Output(_text(data, 'name', key, f'y{i}'), _text(data, 'unit', key, ''),
                              topic, type_name, path,
                              _number(data, 'scale', key, 1.0, nonzero=True),
                              _number(data, 'offset', key, 0.0), low, high))
        previous = known.outputs if known is not None else ()
        topics[topic] = Topic(topic, type_name, cls, stamp, previous + (i,))
    _unique([o.name for o in outputs], 'outputs')
    return tuple(outputs), tuple(topics.values())


def _command(raw: Any) -> Command:
    key = 'command'
    data = _mapping(raw, key, 'command', ('topic', 'type', 'inputs'))
    topic, type_name = _topic(data, key), data['type']
    cls = _message_class(type_name, f'{key}.type')
    inputs = []
    for j, item in enumerate(_list(data['inputs'], f'{key}.inputs')):
        ikey = f'{key}.inputs[{j}]'
        fields = _mapping(item, ikey, 'input', ('field', 'min', 'max', 'safe'))
        path = _checked_leaf(resolve_path(type_name, fields['field'], f'{ikey}.field'),
                             type_name, _FLOATS, f'{ikey}.field', 'a float32 or float64')
        low, high = _number(fields, 'min', ikey), _number(fields, 'max', ikey)
        safe = _number(fields, 'safe', ikey)
        if not low < high:
            raise MappingError(f'{ikey}: min {low:g} must be below max {high:g}')
        if not low <= safe <= high:
            raise MappingError(f'{ikey}.safe: {safe:g} is outside [min, max] = '
                               f'[{low:g}, {high:g}]')
        inputs.append(Input(_text(fields, 'name', ikey, f'u{j}'),
                            _text(fields, 'unit', ikey, ''), path,
                            _number(fields, 'scale', ikey, 1.0, nonzero=True),
                            _number(fields, 'offset', ikey, 0.0), low, high, safe))
    _unique([i.name for i in inputs], f'{key}.inputs')
    texts = [i.field.text for i in inputs]
    _unique(texts, f'{key}.inputs')
    fixed = []
    constants = data.get('fixed', {})
    if not isinstance(constants, dict):
        raise MappingError(f'{key}.fixed: expected a mapping of field paths to values, got '
                           f'{constants!r}')
    for text, value in constants.items():
        fixed.append((resolve_path(type_name, text, f'{key}.fixed.{text}', whole=True),
                      value))
        if not _fits(value, fixed[-1][0].leaf):
            raise MappingError(f'{key}.fixed.{text}: {value!r} does not fit its type '
                               f'{fixed[-1][0].leaf}')
    return Command(topic, type_name, cls, tuple(inputs), tuple(fixed))


def _fits(value: Any, leaf: str) -> bool:
    """Whether a constant of the file fits a field of type `leaf` (a string, a number, or a
    list of them for an array; no messages)."""
    match = re.match(r'^sequence<(.+?)(<=\d+)?>$|^(.+)\[\d+\]$', leaf)
    if match:
        return isinstance(value, list) and all(_fits(v, match.group(1) or match.group(3))
                                               for v in value)
    if leaf == 'string':
        return isinstance(value, str)
    if leaf == 'boolean':
        return isinstance(value, bool)
    kind = float if leaf in _FLOATS else int if leaf in _NUMERIC else None
    return (kind is not None and not isinstance(value, bool)
            and isinstance(value, (int, float) if kind is float else int))


def parse_mapping(data: Any) -> MachineMapping:
    """The mapping of a loaded YAML document, checked (see the module docstring).

    Raises:
        MappingError: one line naming the first wrong key.
    """
    data = _mapping(data, '', '', ('dt', 'stale_timeout', 'outputs', 'command'))
    name = _text(data, 'name', '', 'machine')
    if not name:
        raise MappingError('name: expected a non-empty string')
    dt = _number(data, 'dt', '', positive=True)
    stale = _number(data, 'stale_timeout', '', positive=True)
    if stale <= dt:
        raise MappingError(f'stale_timeout: {stale:g} s must exceed dt = {dt:g} s (the '
                           'controller answers once per dt)')
    outputs, topics = _outputs(_list(data['outputs'], 'outputs'))
    return MachineMapping(name, dt, stale, outputs, topics, _command(data['command']))
