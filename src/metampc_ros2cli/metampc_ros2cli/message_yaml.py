"""ROS messages <-> YAML and CSV, in the formats ros2cli prints and reads (Jazzy).

One conversion for every message type, through rosidl's introspection: a generated class lists
its fields in ``get_fields_and_field_types()`` (in .msg order) and their rosidl_parser types in
``SLOT_TYPES``. What `ros2 topic echo` prints is :func:`to_yaml` followed by a line ``---``;
what `ros2 topic pub` and `ros2 service call` read is a YAML mapping, applied by
:func:`set_fields`. Truncation (``--truncate-length``), ``--no-arr`` and ``--no-str`` behave as
in rosidl_runtime_py, which is not published for the pip-installed ROS.
"""
import array
import importlib
import sys
from collections import OrderedDict
from typing import Any, List, Mapping, Optional, Tuple

import yaml
from rosidl_parser.definition import (AbstractNestedType, AbstractString, AbstractWString, Array,
                                      BasicType, BoundedSequence, NamedType, NamespacedType)

DEFAULT_TRUNCATE_LENGTH = 128     # ros2 topic echo's default --truncate-length


def _np() -> Any:
    """numpy, imported at the first conversion: the `ros2` parser imports this module, and the
    verbs that convert no message need not pay for numpy (0.2 s of an idle start)."""
    import numpy
    return numpy


def _is_sequence(value: Any) -> bool:
    return isinstance(value, (list, tuple, array.array, _np().ndarray))


class _Dumper(yaml.SafeDumper):
    """A dumper that writes OrderedDicts as plain mappings, in their order (as ros2cli)."""


_Dumper.add_representer(OrderedDict, lambda d, data: d.represent_mapping(
    'tag:yaml.org,2002:map', data.items(), flow_style=None))


def fields(msg: Any) -> 'OrderedDict[str, Any]':
    """{field name: rosidl_parser type} of a message (instance or class), in .msg order."""
    return OrderedDict(zip(msg.get_fields_and_field_types().keys(), msg.SLOT_TYPES))


def type_name(t: Any) -> str:
    """The name ros2cli shows for a field's element type ('float64', 'string', 'pkg/Type')."""
    if isinstance(t, BasicType):
        return t.typename
    if isinstance(t, AbstractString):
        return 'string'
    if isinstance(t, AbstractWString):
        return 'wstring'
    if isinstance(t, NamedType):
        return t.name
    if isinstance(t, NamespacedType):
        return '/'.join(t.namespaced_name())
    return 'unknown'


def _array_info(value: Any, t: Any) -> str:
    """--no-arr's placeholder for an array or sequence field."""
    name = type_name(t.value_type)
    if isinstance(t, Array):
        return f'<array type: {name}[{t.size}]>'
    if isinstance(t, BoundedSequence):
        return f'<sequence type: {name}[{t.maximum_size}], length: {len(value)}>'
    return f'<sequence type: {name}, length: {len(value)}>'


def _value(value: Any, t: Any, limit: Optional[int], no_arr: bool, no_str: bool) -> Any:
    """One field's value as plain YAML data (truncated as ros2cli truncates)."""
    if isinstance(value, bytes):
        text = ''.join(chr(c) for c in value[:limit])
        return text + '...' if limit is not None and len(value) > limit else text
    if isinstance(value, str):
        if no_str:
            return f'<string length: <{len(value)}>>'
        return value[:limit] + '...' if limit is not None and len(value) > limit else value
    if _is_sequence(value):
        if no_arr and t is not None:
            return _array_info(value, t)
        kind = tuple if isinstance(value, tuple) else list
        items = [_value(v, None, limit, no_arr, no_str) for v in value[:limit]]
        return kind(items + ['...'] if limit is not None and len(value) > limit else items)
    if isinstance(value, _np().generic):
        return value.item()
    if isinstance(value, (bool, int, float)):
        return value
    return to_dict(value, truncate_length=limit, no_arr=no_arr, no_str=no_str)


def to_dict(msg: Any, *, truncate_length: Optional[int] = None, no_arr: bool = False,
            no_str: bool = False) -> 'OrderedDict[str, Any]':
    """A message as an OrderedDict of plain values (nested messages as OrderedDicts)."""
    return OrderedDict((name, _value(getattr(msg, name), t, truncate_length, no_arr, no_str))
                       for name, t in fields(msg).items())


def to_yaml(msg: Any, *, truncate_length: Optional[int] = None, no_arr: bool = False,
            no_str: bool = False, flow_style: bool = False) -> str:
    """What `ros2 topic echo` prints for one message (block style unless `flow_style`)."""
    return yaml.dump(to_dict(msg, truncate_length=truncate_length, no_arr=no_arr,
                             no_str=no_str),
                     Dumper=_Dumper, allow_unicode=True, width=sys.maxsize,
                     default_flow_style=flow_style)


def to_csv(msg: Any, *, truncate_length: Optional[int] = None, no_arr: bool = False,
           no_str: bool = False) -> str:
    """What `ros2 topic echo --csv` prints: every leaf value, depth first, comma-separated."""
    def leaf(value: Any, t: Any) -> str:
        if _is_sequence(value):
            if no_arr and t is not None:
                return _array_info(value, t)
            parts = [leaf(v, None) for v in value[:truncate_length]]
            if truncate_length is not None and len(value) > truncate_length:
                parts.append('...')
            return ','.join(parts)
        if isinstance(value, (str, bytes)):
            if no_str and isinstance(value, str):
                return f'<string length: <{len(value)}>>'
            if truncate_length is not None and len(value) > truncate_length:
                value = value[:truncate_length] + (b'...' if isinstance(value, bytes) else '...')
            return str(value)
        if isinstance(value, (bool, int, float, _np().generic)):
            return str(value)
        return to_csv(value, truncate_length=truncate_length, no_arr=no_arr, no_str=no_str)
    return ','.join(leaf(getattr(msg, name), t) for name, t in fields(msg).items())


def message_class_of(t: NamespacedType) -> type:
    """The Python class of a nested message type."""
    module = importlib.import_module('.'.join(t.namespaces))
    return getattr(module, t.name)


def set_fields(msg: Any, values: Mapping[str, Any],
               stamps: Optional[List[Tuple[Any, str]]] = None) -> None:
    """Set the fields named in `values` (a YAML mapping, nested for nested messages).

    With a `stamps` list (`ros2 topic pub`), a std_msgs/Header given as ``auto`` and a
    builtin_interfaces/Time given as ``now`` are left for the caller to stamp at each publish:
    their (object, attribute) pairs are appended to `stamps`.

    Raises:
        ValueError: a name the message does not have, or a value its field cannot take; the
            text names the field (ros2cli prints it after 'Failed to populate field: ').
    """
    if not isinstance(values, Mapping):
        raise ValueError(f"Value '{values}' is expected to be a dictionary but is a "
                         f'{type(values).__name__}')
    slots = fields(msg)
    for name, value in values.items():
        if name not in slots:
            raise ValueError(f"'{type(msg).__name__}' object has no attribute '{name}'")
        t = slots[name]
        if stamps is not None and isinstance(t, NamespacedType):
            full = '/'.join(t.namespaced_name())
            if (full, value) == ('std_msgs/msg/Header', 'auto'):
                setattr(msg, name, type(getattr(msg, name))())
                stamps.append((getattr(msg, name), 'stamp'))
                continue
            if (full, value) == ('builtin_interfaces/msg/Time', 'now'):
                stamps.append((msg, name))
                continue
        try:
            setattr(msg, name, _typed(getattr(msg, name), t, value, stamps))
        except (AssertionError, TypeError, ValueError, OverflowError) as err:
            raise ValueError(f'{name}: {_reason(err)}') from None


def _reason(err: Exception) -> str:
    """The first line of an error from a generated setter (its assertions are long)."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


_INT_BITS = {'int8': (True, 8), 'uint8': (False, 8), 'int16': (True, 16),
             'uint16': (False, 16), 'int32': (True, 32), 'uint32': (False, 32),
             'int64': (True, 64), 'uint64': (False, 64), 'char': (False, 8)}


def _typed(current: Any, t: Any, value: Any,
           stamps: Optional[List[Tuple[Any, str]]] = None) -> Any:
    """`value` converted to what field type `t` holds (`current` is the field's value).

    The generated setters of Jazzy check nothing unless ROS_PYTHON_CHECK_FIELDS=1, so a wrong
    value would only fail when published; it is refused here, naming what the field takes.
    """
    if isinstance(t, AbstractNestedType):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f'expected a list, got {value!r}')
        if isinstance(t, Array) and len(value) != t.size:
            raise ValueError(f'expected {t.size} values, got {len(value)}')
        if isinstance(t, BoundedSequence) and len(value) > t.maximum_size:
            raise ValueError(f'expected at most {t.maximum_size} values, got {len(value)}')
        if isinstance(t.value_type, NamespacedType):
            cls = message_class_of(t.value_type)
            out: List[Any] = []
            for item in value:
                sub = cls()
                set_fields(sub, item, stamps)
                out.append(sub)
            return out
        items = [_basic(t.value_type, v) for v in value]
        np = _np()
        if isinstance(current, np.ndarray):
            return np.array(items, dtype=current.dtype)
        if isinstance(current, array.array):
            return array.array(current.typecode, items)
        return items
    if isinstance(t, NamespacedType):
        sub = type(current)()
        set_fields(sub, value, stamps)
        return sub
    return _basic(t, value)


def _basic(t: Any, value: Any) -> Any:
    """A value of a basic or string type, checked as the field's type requires."""
    if isinstance(t, (AbstractString, AbstractWString)):
        if not isinstance(value, str):
            raise ValueError(f'expected a string, got {value!r}')
        return value
    name = t.typename
    if name == 'boolean':
        if not isinstance(value, bool):
            raise ValueError(f'expected true or false, got {value!r}')
        return value
    if name == 'octet':         # echo shows a byte as its character; an integer is taken too
        if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 256:
            return bytes([value])
        if isinstance(value, str) and len(value) == 1 and ord(value) < 256:
            return value.encode('latin-1')
        raise ValueError(f'expected a byte (0-255 or one character), got {value!r}')
    if name in _INT_BITS:
        signed, bits = _INT_BITS[name]
        low, high = (-2 ** (bits - 1), 2 ** (bits - 1) - 1) if signed else (0, 2 ** bits - 1)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ValueError(f'expected an integer in [{low}, {high}] ({name}), got {value!r}')
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f'expected a number ({name}), got {value!r}')
    return float(value)


def from_yaml(cls: type, text: str, stamps: Optional[List[Tuple[Any, str]]] = None) -> Any:
    """A message of class `cls` with the fields given as a YAML mapping in `text` (`stamps`:
    see :func:`set_fields`).

    Raises:
        ValueError: text that is not YAML, or not a mapping ('The passed value needs to be a
            dictionary in YAML format', as ros2cli), or a field that cannot take its value.
    """
    try:
        values = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ValueError(f'The passed value is not valid YAML: {_reason(err)}') from None
    if values is None:
        values = {}
    if not isinstance(values, dict):
        raise ValueError('The passed value needs to be a dictionary in YAML format')
    msg = cls()
    set_fields(msg, values, stamps)
    return msg
