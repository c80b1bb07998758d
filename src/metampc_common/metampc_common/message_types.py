"""ROS interface type names ('pkg/msg/Type') and their generated Python classes. No rclpy.

Shared by the nodes that take a type by name (the recorder, the player, the live view, the
`ros2` verbs, the machine bridge) and by tools that only read recordings.
"""
import importlib
import re
from typing import Tuple

_ROS_NAME = r'[a-zA-Z][a-zA-Z0-9_]*'
_TYPE_NAME = re.compile(rf'^({_ROS_NAME})/(?:({_ROS_NAME})/)?({_ROS_NAME})$')


def split_type_name(type_name: str) -> Tuple[str, str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'msg', 'Type'); ValueError for anything else."""
    match = _TYPE_NAME.match(type_name)
    if match is None:
        raise ValueError(f'invalid type name {type_name!r}')
    package, namespace, name = match.groups()
    return package, namespace or 'msg', name


def message_class(type_name: str) -> type:
    """The generated Python class of 'pkg/msg/Type' (ValueError for a malformed name,
    ImportError/AttributeError if it is not installed)."""
    package, namespace, name = split_type_name(type_name)
    return getattr(importlib.import_module(f'{package}.{namespace}'), name)
