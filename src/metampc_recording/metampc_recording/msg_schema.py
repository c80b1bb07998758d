"""Complete message definitions (MCAP schema `ros2msg` / `ros2idl`), as rosbag2 writes them.

A recording carries, for every message type, the type's own interface file followed by the
files of every type it uses, recursively, so that a reader with no ROS installation can decode
the CDR payloads. This module builds that text byte for byte as rosbag2's
``LocalMessageDefinitionSource`` (Jazzy) does: dependencies found by a regular expression on
the text, sorted, depth first, each once, each after ``"\\n"``, 80 ``=`` and ``MSG: pkg/Type``;
files looked up through the ament index (``<prefix>/share/<pkg>/msg/<Type>.msg``), falling back
to ``.idl`` files (``IDL: pkg/msg/Type``, encoding ``ros2idl``). Nothing here imports rclpy.
The layout: docs/recording.md.
"""
import os
import re
from dataclasses import dataclass
from typing import Dict, List, Optional, Set, Tuple

from metampc_common.message_types import split_type_name

DELIMITER = '=' * 80 + '\n'
_MARKER = os.path.join('share', 'ament_index', 'resource_index', 'packages')
# rosbag2's MSG_FIELD_TYPE_REGEX and IDL_FIELD_TYPE_REGEX (ECMAScript: '^' is start of text only).
_MSG_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
_PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string'})
_MAX_DEPTH = 50


class DefinitionNotFoundError(LookupError):
    """No interface file of the requested format exists for a type."""


@dataclass(frozen=True)
class MessageDefinition:
    """A complete definition: MCAP schema `encoding` ('ros2msg' or 'ros2idl') and its `text`."""

    encoding: str
    text: str


def package_share_directory(package: str, prefixes: Optional[List[str]] = None) -> str:
    """`<prefix>/share/<package>` of the first ament prefix that registers `package`.

    Args:
        package: ROS package name.
        prefixes: install prefixes to search; default: ``AMENT_PREFIX_PATH`` in order.

    Raises:
        DefinitionNotFoundError: no prefix has the package in its ament index.
    """
    if prefixes is None:
        prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes:
        if os.path.isfile(os.path.join(prefix, _MARKER, package)):
            return os.path.join(prefix, 'share', package)
    raise DefinitionNotFoundError(f'package {package!r} is not in the ament index')


def _dependencies(fmt: str, text: str, package: str) -> List[str]:
    """Sorted dependency names of one interface file (rosbag2's std::set<std::string> order)."""
    found: Set[str] = set()
    if fmt == 'msg':
        for match in _MSG_FIELD_TYPE.finditer(text):
            name = match.group(1)
            if name in _PRIMITIVES:
                continue
            found.add(name if '/' in name else f'{package}/{name}')
    else:
        found.update(m.group(1) for m in _IDL_INCLUDE.finditer(text))
    return sorted(found)


class DefinitionSource:
    """Builds complete definitions from interface files, caching every file it reads.

    Args:
        prefixes: ament prefixes to search (default: ``AMENT_PREFIX_PATH`` at each lookup).
    """

    def __init__(self, prefixes: Optional[List[str]] = None):
        self._prefixes = prefixes
        self._files: Dict[Tuple[str, str], Tuple[str, List[str]]] = {}

    def _load(self, fmt: str, type_name: str) -> Tuple[str, List[str]]:
        key = (fmt, type_name)
        if key not in self._files:
            package, namespace, name = split_type_name(type_name)
            share = package_share_directory(package, self._prefixes)
            path = os.path.join(share, namespace, f'{name}.{fmt}')
            if not os.path.isfile(path):
                raise DefinitionNotFoundError(f'no {path}')
            with open(path, encoding='utf-8') as f:
                text = f.read()
            self._files[key] = (text, _dependencies(fmt, text, package))
        return self._files[key]

    def _full_text(self, fmt: str, root: str) -> str:
        seen: Set[str] = set()
        header = 'MSG: ' if fmt == 'msg' else 'IDL: '

        def append(type_name: str, depth: int) -> str:
            if depth <= 0:
                raise RecursionError(f'definition of {root} nests too deeply')
            text, deps = self._load(fmt, type_name)
            for dep in deps:
                if dep not in seen:
                    seen.add(dep)
                    text += '\n' + DELIMITER + header + dep + '\n' + append(dep, depth - 1)
            return text

        if fmt == 'msg':
            return append(root, _MAX_DEPTH)
        return DELIMITER + header + root + '\n' + append(root, _MAX_DEPTH)

    def get(self, type_name: str) -> MessageDefinition:
        """Complete definition of `type_name` ('pkg/msg/Type'), '.msg' first, else '.idl'.

        Raises:
            DefinitionNotFoundError: neither a '.msg' nor an '.idl' definition was found.
        """
        try:
            return MessageDefinition('ros2msg', self._full_text('msg', type_name))
        except DefinitionNotFoundError:
            return MessageDefinition('ros2idl', self._full_text('idl', type_name))
