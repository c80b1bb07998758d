"""ROS 2's YAML launch format (launch_yaml, launch_ros; Jazzy), the subset that brings up a
graph of nodes, read by the format's rules so that the same file runs with the real
`ros2 launch`: a `launch:` list of `arg` (name, default, description) and `node` (pkg, exec,
name, namespace, output, param [{name, value}], remap [{from, to}]); `$(var NAME)` is an arg's
value (its default, or `NAME:=VALUE` on the command line). A parameter value is typed as
launch_ros types it: a string (after substitution) read as YAML, any other YAML value kept, the
strings of a list left strings. Everything else of the format (`include`, `group`, `let`,
`executable`, other substitutions, parameter files...) is refused by name (:class:`LaunchError`,
one line). An example and the shipped files: docs/nodes.md. No rclpy here.
"""
import re
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import yaml

NODE_KEYS = ('pkg', 'exec', 'name', 'namespace', 'output', 'param', 'remap')
OUTPUTS = ('log', 'screen', 'both')
SUBSTITUTION = re.compile(r'\$\(([^()]*)\)')


class LaunchError(ValueError):
    """A launch file or argument this reader cannot run; the message is one line."""


@dataclass
class Arg:
    name: str
    default: Optional[str] = None
    description: str = ''


@dataclass
class NodeSpec:
    pkg: str
    exec: str
    name: Optional[str] = None
    namespace: Optional[str] = None
    output: str = 'log'
    params: Dict[str, Any] = field(default_factory=dict)
    remaps: List[Tuple[str, str]] = field(default_factory=list)


def load(text: str, source: str = 'the launch file') -> Tuple[List[Arg], List[dict]]:
    """The declared args and the node entries (as written) of a launch file's text."""
    try:
        root = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise LaunchError(f'{source} is not YAML: {" ".join(str(err).split())}') from None
    if not isinstance(root, dict) or list(root) != ['launch'] \
            or not isinstance(root['launch'], list):
        raise LaunchError(f"{source}: the one top-level key must be 'launch', a list")
    args, nodes = [], []
    for entry in root['launch']:
        if not isinstance(entry, dict) or len(entry) != 1:
            raise LaunchError(f'{source}: each entry of launch must be one action, '
                              f'not {entry!r}')
        (kind, body), = entry.items()
        if kind not in ('arg', 'node'):
            raise LaunchError(f"{source}: '{kind}' is not supported here (only arg and node; "
                              "run the file with ROS's own ros2 launch)")
        if not isinstance(body, dict):
            raise LaunchError(f'{source}: {kind} must be a mapping, not {body!r}')
        allowed = ('name', 'default', 'description') if kind == 'arg' else NODE_KEYS
        unknown = sorted(set(body) - set(allowed))
        if unknown:
            raise LaunchError(f"{source}: {kind} has unsupported keys {unknown} (this reader "
                              f"knows {', '.join(allowed)})")
        if kind == 'arg':
            if not isinstance(body.get('name'), str):
                raise LaunchError(f'{source}: an arg needs a name')
            default = body.get('default')
            args.append(Arg(body['name'], None if default is None else str(default),
                            str(body.get('description', ''))))
        else:
            for key in ('pkg', 'exec'):
                if not isinstance(body.get(key), str):
                    raise LaunchError(f'{source}: a node needs {key} (a string)')
            nodes.append(body)
    return args, nodes


def values(args: Sequence[Arg], given: Sequence[str]) -> Dict[str, str]:
    """Each arg's value: `NAME:=VALUE` of `given` (the command line), else its default."""
    declared = {a.name: a for a in args}
    out = {a.name: a.default for a in args if a.default is not None}
    for item in given:
        name, sep, value = item.partition(':=')
        if not sep or not name:
            raise LaunchError(f"malformed launch argument '{item}', expected format "
                              "'<name>:=<value>'")
        if name not in declared:
            raise LaunchError(f"unknown launch argument '{name}' (the file declares "
                              f"{', '.join(sorted(declared)) or 'none'})")
        out[name] = value
    missing = [a.name for a in args if a.name not in out]
    if missing:
        raise LaunchError(f'missing required launch argument(s) {missing}: give NAME:=VALUE')
    return out


def substitute(text: str, variables: Dict[str, str]) -> str:
    """`text` with each `$(var NAME)` replaced by its value."""
    def one(match: 're.Match') -> str:
        words = match.group(1).split()
        if len(words) != 2 or words[0] != 'var':
            raise LaunchError(f"the substitution '{match.group(0)}' is not supported here "
                              '(only $(var NAME))')
        if words[1] not in variables:
            raise LaunchError(f"'{match.group(0)}': no arg named '{words[1]}' is declared")
        return variables[words[1]]
    return SUBSTITUTION.sub(one, text)


def param_value(value: Any, variables: Dict[str, str]) -> Any:
    """A parameter's value as launch_ros types it (module docstring)."""
    if isinstance(value, str):
        text = substitute(value, variables)
        if not text:
            return ''
        try:
            typed = yaml.safe_load(text)
        except yaml.YAMLError:
            raise LaunchError(f"the parameter value '{text}' is not a YAML value") from None
        if isinstance(typed, dict) or typed is None:
            raise LaunchError(f"the parameter value '{text}' is not a scalar or a list")
        return typed
    if isinstance(value, list):
        return [substitute(v, variables) if isinstance(v, str) else v for v in value]
    if isinstance(value, (bool, int, float)):
        return value
    raise LaunchError(f'the parameter value {value!r} is not a scalar or a list')


def _pairs(body: dict, key: str, names: Tuple[str, str]) -> List[dict]:
    items = body.get(key) or []
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise LaunchError(f'{key} of a node must be a list of mappings')
    for item in items:
        if sorted(item) != sorted(names):
            raise LaunchError(f'each {key} of a node has exactly {" and ".join(names)}, not '
                              f'{sorted(item)} (this reader has no parameter files or '
                              'groups)')
    return items


def nodes(entries: Sequence[dict], variables: Dict[str, str]) -> List[NodeSpec]:
    """The node entries of :func:`load` with their substitutions made."""
    out = []
    for body in entries:
        text = {k: substitute(str(body[k]), variables)
                for k in ('pkg', 'exec', 'name', 'namespace', 'output') if k in body}
        output = text.get('output', 'log')
        if output not in OUTPUTS:
            raise LaunchError(f"output '{output}' of node {text['exec']}: one of "
                              f"{', '.join(OUTPUTS)}")
        namespace = text.get('namespace')
        if namespace is not None and not namespace.startswith('/'):
            namespace = '/' + namespace
        out.append(NodeSpec(
            text['pkg'], text['exec'], text.get('name'), namespace, output,
            {substitute(str(p['name']), variables): param_value(p['value'], variables)
             for p in _pairs(body, 'param', ('name', 'value'))},
            [(substitute(str(r['from']), variables), substitute(str(r['to']), variables))
             for r in _pairs(body, 'remap', ('from', 'to'))]))
    return out


def read(text: str, given: Sequence[str], source: str = 'the launch file') -> List[NodeSpec]:
    """The nodes a launch file's text starts with the command line's `NAME:=VALUE`s."""
    args, entries = load(text, source)
    return nodes(entries, values(args, given))
