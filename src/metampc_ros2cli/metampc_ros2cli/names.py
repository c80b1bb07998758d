"""`list`, `type` and `find` of `ros2 topic` and `ros2 service`: one listing of the graph's
(name, types) pairs, with each family's flag names (``--count-topics``,
``--include-hidden-services``...), output and exit statuses as ros2cli."""
import functools
from typing import Any, Callable, Dict, List, Tuple

from metampc_ros2cli import api, daemon, direct

Query = Callable[[Any], List[Tuple[str, List[str]]]]     # node -> (name, types) pairs


def add_verbs(verbs: Any, kind: str, query: Query, example_type: str) -> Dict[str, Any]:
    """Add list, type and find for `kind` ('topic' or 'service'); returns their parsers."""
    plural = f'{kind}s'
    out = {}
    p = out['list'] = verbs.add_parser('list', help=f'Output a list of available {plural}')
    p.add_argument('-t', '--show-types', action='store_true',
                   help=f'Additionally show the {kind} type')
    p.add_argument('-c', f'--count-{plural}', dest='count', action='store_true',
                   help=f'Only display the number of {plural} discovered')
    p.set_defaults(main=functools.partial(list_names, query))

    p = out['type'] = verbs.add_parser('type', help=f"Output a {kind}'s type")
    p.add_argument('name', metavar=f'{kind}_name', help=f'Name of the ROS {kind} to get type')
    p.set_defaults(main=functools.partial(print_type, query))

    p = out['find'] = verbs.add_parser('find', help=f'Output a list of available {plural} of '
                                       'a given type')
    p.add_argument('type', metavar=f'{kind}_type', help=f'Name of the ROS {kind} type to '
                   f"filter for (e.g. '{example_type}')")
    p.add_argument('-c', f'--count-{plural}', dest='count', action='store_true',
                   help=f'Only display the number of {plural} discovered')
    p.set_defaults(main=functools.partial(find, query))
    for p in out.values():
        p.add_argument(f'--include-hidden-{plural}', dest='include_hidden', action='store_true',
                       help=f'Consider hidden {plural} as well')
        direct.add_arguments(p)
    for verb in ('list', 'find'):   # the graph as a whole: the daemon's (type waits for one)
        daemon.add_arguments(out[verb])
    return out


def listing(query: Query, node: Any, include_hidden: bool) -> List[Tuple[str, List[str]]]:
    return api.visible(query(node), include_hidden)


def list_names(query: Query, args: Any) -> int:
    with daemon.graph(args) as node:
        pairs = listing(query, node, args.include_hidden)
    if args.count:
        print(len(pairs))
    else:
        for name, types in pairs:
            print(f'{name} [{", ".join(types)}]' if args.show_types else name)
    return 0


def print_type(query: Query, args: Any) -> int:
    with direct.DirectNode(args) as node:
        name = api.expand(node, args.name)
        types = direct.wait_for(node, lambda: dict(listing(query, node,
                                                           args.include_hidden)).get(name))
    for t in types or ():
        print(t)
    return 0 if types else 1


def find(query: Query, args: Any) -> int:
    with daemon.graph(args) as node:
        found = [n for n, t in listing(query, node, args.include_hidden) if args.type in t]
    if args.count:
        print(len(found))
    elif found:
        print(*found, sep='\n')
    return 0
