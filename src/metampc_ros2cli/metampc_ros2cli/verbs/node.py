"""`ros2 node list|info`, as ros2node (Jazzy) prints them."""
import sys
from typing import Any, List

from metampc_ros2cli import api, daemon, direct
from metampc_ros2cli.cli import add_family

HIDDEN_NODE_PREFIX = '_'


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'node', 'Various node related sub-commands')
    p = verbs.add_parser('list', help='Output a list of available nodes')
    p.add_argument('-a', '--all', action='store_true',
                   help='Display all nodes even hidden ones')
    p.add_argument('-c', '--count-nodes', action='store_true',
                   help='Only display the number of nodes discovered')
    direct.add_arguments(p)
    daemon.add_arguments(p)
    p.set_defaults(main=list_nodes)

    p = verbs.add_parser('info', help='Output information about a node')
    p.add_argument('node_name', help='Node name to request information')
    p.add_argument('--include-hidden', action='store_true',
                   help='Display hidden topics, services, and actions as well')
    direct.add_arguments(p)
    daemon.add_arguments(p)
    p.set_defaults(main=info)


def full_names(node: Any, include_hidden: bool) -> List[str]:
    """'/namespace/name' of every node in the graph (hidden ones only if asked)."""
    return [ns + ('' if ns.endswith('/') else '/') + name
            for name, ns in node.get_node_names_and_namespaces()
            if include_hidden or (name and not name.startswith(HIDDEN_NODE_PREFIX))]


def list_nodes(args: Any) -> int:
    with daemon.graph(args) as node:
        names = sorted(full_names(node, args.all))
    if args.count_nodes:
        print(len(names))
    elif names:
        if len(set(names)) < len(names):
            print('WARNING: Be aware that there are nodes in the graph that share an exact '
                  'name, which can have unintended side effects.', file=sys.stderr)
        print(*names, sep='\n')
    return 0


SECTIONS = (('Subscribers', 'get_subscriber_names_and_types_by_node'),
            ('Publishers', 'get_publisher_names_and_types_by_node'),
            ('Service Servers', 'get_service_names_and_types_by_node'),
            ('Service Clients', 'get_client_names_and_types_by_node'),
            ('Action Servers', 'get_action_server_names_and_types_by_node'),
            ('Action Clients', 'get_action_client_names_and_types_by_node'))


def info(args: Any) -> Any:
    """From the daemon's graph, as ros2cli's: an unknown node is refused at once (a node of
    the verb's own, --no-daemon, waits up to direct.DISCOVERY_GRACE_S for it)."""
    with daemon.graph(args) as node:
        proxy = isinstance(node, daemon.GraphProxy)
        count = full_names(node, args.include_hidden).count(args.node_name)
        if not count and not proxy:
            count = direct.wait_for(node, lambda: full_names(node, args.include_hidden).count(
                args.node_name))
        if not count:
            return f"Unable to find node '{args.node_name}'"
        if count > 1:
            print(f'There are {count} nodes in the graph with the exact name '
                  f'"{args.node_name}". You are seeing information about only one of them.',
                  file=sys.stderr)
        namespace, _, name = args.node_name.rpartition('/')
        namespace = namespace or '/'
        print(args.node_name)
        for title, call in SECTIONS:
            print(f'  {title}:')
            query = getattr(node, call) if proxy else daemon.by_node(node, call)
            rows = api.visible(query(name, namespace), args.include_hidden)
            print(*[f'    {n}: {", ".join(t)}' for n, t in rows], sep='\n')
    return 0
