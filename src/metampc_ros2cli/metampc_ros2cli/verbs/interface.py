"""`ros2 interface list|show|package|packages|proto`, as ros2interface (Jazzy) prints them.

The text of an interface comes from its file in the ament index (share/PKG/msg/Type.msg), as
ros2interface reads it; `show` expands the nested types below their field, indented by a tab.
"""
import os
import re
from typing import Any, Dict, List

from metampc_ros2cli import api, message_yaml
from metampc_ros2cli.cli import add_family

KINDS = ('msg', 'srv', 'action')
_MARKER = os.path.join('share', 'ament_index', 'resource_index', 'rosidl_interfaces')
_FIELD = re.compile(r'^\s*([a-zA-Z0-9_/]+)(\[[^\]]*\])?\s+\w+')
_PRIMITIVES = frozenset({'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8',
                         'int16', 'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string',
                         'wstring'})


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'interface', 'Show information about ROS interfaces')
    p = verbs.add_parser('list', help='List all interface types available')
    group = p.add_mutually_exclusive_group()
    group.add_argument('-m', '--only-msgs', action='store_true', help='Print out only the '
                       'message types')
    group.add_argument('-s', '--only-srvs', action='store_true', help='Print out only the '
                       'service types')
    group.add_argument('-a', '--only-actions', action='store_true', help='Print out only the '
                       'action types')
    p.set_defaults(main=list_interfaces)

    p = verbs.add_parser('package', help='Output a list of available interface types within '
                         'one package')
    p.add_argument('package_name', help="Name of the ROS package (e.g.: 'example_interfaces')")
    p.set_defaults(main=package)

    p = verbs.add_parser('packages', help='Output a list of packages that provide interfaces')
    group = p.add_mutually_exclusive_group()
    for short, kind in (('-m', 'msgs'), ('-s', 'srvs'), ('-a', 'actions')):
        group.add_argument(short, f'--only-{kind}', action='store_true',
                           help=f'Print out only the packages that provide {kind}')
    p.set_defaults(main=packages)

    p = verbs.add_parser('show', help='Output the interface definition')
    p.add_argument('type', help="Show an interface definition (e.g. 'example_interfaces/msg/"
                   "String')")
    p.add_argument('--all-comments', action='store_true', help='Show all comments, including '
                   'for nested interface definitions')
    p.add_argument('--no-comments', action='store_true', help='Show no comments or whitespace')
    p.set_defaults(main=show)

    p = verbs.add_parser('proto', help='Output an interface prototype')
    p.add_argument('type', help="Show an interface definition (e.g. 'example_interfaces/msg/"
                   "String')")
    p.add_argument('--no-quotes', action='store_true', help='if true output has no outer '
                   'quotes.')
    p.set_defaults(main=proto)


def interfaces() -> Dict[str, List[str]]:
    """{package: ['msg/Type', 'srv/Type', ...]} from the ament index (first prefix wins)."""
    found: Dict[str, List[str]] = {}
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        index = os.path.join(prefix, _MARKER)
        if not prefix or not os.path.isdir(index):
            continue
        for pkg in sorted(os.listdir(index)):
            if pkg in found:
                continue
            with open(os.path.join(index, pkg)) as f:
                lines = [ln.strip() for ln in f.read().splitlines()]
            found[pkg] = sorted({os.path.splitext(ln)[0] for ln in lines
                                 if ln.split('/')[0] in KINDS and ln.endswith(('.msg', '.srv',
                                                                               '.action'))})
    return found


def _wanted(args: Any) -> tuple:
    for kind, flag in (('msg', 'only_msgs'), ('srv', 'only_srvs'), ('action', 'only_actions')):
        if getattr(args, flag, False):
            return (kind,)
    return KINDS


def list_interfaces(args: Any) -> int:
    names = interfaces()
    for kind, title in (('msg', 'Messages'), ('srv', 'Services'), ('action', 'Actions')):
        if kind not in _wanted(args):
            continue
        print(f'{title}:')
        for pkg, types in sorted(names.items()):
            for t in types:
                if t.startswith(kind + '/'):
                    print(f'    {pkg}/{t}')
    return 0


def package(args: Any) -> Any:
    types = interfaces().get(args.package_name)
    if types is None:
        return f"Unknown package '{args.package_name}'"
    for t in types:
        print(f'{args.package_name}/{t}')
    return 0


def packages(args: Any) -> int:
    kinds = _wanted(args)
    for pkg, types in sorted(interfaces().items()):
        if any(t.split('/')[0] in kinds for t in types):
            print(pkg)
    return 0


def _file(type_name: str) -> str:
    """The text of 'pkg/kind/Type' from its interface file."""
    from metampc_recording.msg_schema import DefinitionNotFoundError, package_share_directory
    parts = type_name.split('/')
    if len(parts) != 3:
        raise RuntimeError(f"Invalid name '{type_name}'. Expected three parts separated by '/'")
    pkg, kind, name = parts
    try:
        path = os.path.join(package_share_directory(pkg), kind, f'{name}.{kind}')
    except DefinitionNotFoundError:
        path = ''
    if not os.path.isfile(path):
        raise RuntimeError(f"Unknown interface '{type_name}'" if path or not pkg else
                           f"Unknown package '{pkg}'")
    with open(path) as f:
        return f.read()


def _lines(type_name: str, depth: int, comments: bool, nested_comments: bool,
           out: List[str]) -> None:
    """Append the lines `show` prints for `type_name`, indented `depth` tabs; each field of a
    message type is followed by that type's lines, one tab deeper (as ros2interface)."""
    pkg = type_name.split('/')[0]
    for line in _file(type_name).splitlines():
        line = line.rstrip()
        code = line.split('#', 1)[0].rstrip()
        if not comments:
            if not code:
                continue
            line = code.strip() if code != line else line
        out.append('\t' * depth + line if line else '')
        match = _FIELD.match(code)
        if not match or '=' in code or match.group(1) in _PRIMITIVES:
            continue
        nested = match.group(1) if '/' in match.group(1) else f'{pkg}/{match.group(1)}'
        nested_pkg, _, nested_name = nested.rpartition('/')
        _lines(f'{nested_pkg.split("/")[0]}/msg/{nested_name}', depth + 1, nested_comments,
               nested_comments, out)


def show(args: Any) -> Any:
    out: List[str] = []
    _lines(args.type, 0, not args.no_comments, args.all_comments, out)
    print('\n'.join(out))
    return 0


def proto(args: Any) -> Any:
    parts = args.type.split('/')
    kind = parts[1] if len(parts) == 3 else 'msg'
    cls = api.interface_class(args.type, kind)
    text = message_yaml.to_yaml(cls())
    print(text if args.no_quotes else f'"{text}"')
    return 0
