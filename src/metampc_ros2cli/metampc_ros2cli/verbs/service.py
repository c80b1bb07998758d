"""`ros2 service list|type|find|call`, as ros2service (Jazzy) prints and exits."""
import sys
import time
from typing import Any, List

from metampc_ros2cli import api, direct, message_yaml
from metampc_ros2cli.cli import add_family


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'service', 'Various service related sub-commands')

    p = verbs.add_parser('list', help='Output a list of available services')
    p.add_argument('-t', '--show-types', action='store_true',
                   help='Additionally show the service type')
    p.add_argument('-c', '--count-services', action='store_true',
                   help='Only display the number of services discovered')
    p.add_argument('--include-hidden-services', action='store_true',
                   help='Consider hidden services as well')
    direct.add_arguments(p)
    p.set_defaults(main=list_services)

    p = verbs.add_parser('type', help="Output a service's type")
    p.add_argument('service_name', help="Name of the ROS service to get type (e.g. "
                   "'/add_two_ints')")
    p.add_argument('--include-hidden-services', action='store_true',
                   help='Consider hidden services as well')
    direct.add_arguments(p)
    p.set_defaults(main=service_type)

    p = verbs.add_parser('find', help='Output a list of available services of a given type')
    p.add_argument('service_type', help="Name of the ROS service type to filter for (e.g. "
                   "'rcl_interfaces/srv/ListParameters')")
    p.add_argument('-c', '--count-services', action='store_true',
                   help='Only display the number of services discovered')
    p.add_argument('--include-hidden-services', action='store_true',
                   help='Consider hidden services as well')
    direct.add_arguments(p)
    p.set_defaults(main=find)

    p = verbs.add_parser('call', help='Call a service')
    p.add_argument('service_name', help="Name of the ROS service to call to (e.g. "
                   "'/add_two_ints')")
    p.add_argument('service_type', help="Type of the ROS service (e.g. 'std_srvs/srv/Empty')")
    group = p.add_mutually_exclusive_group()
    group.add_argument('values', nargs='?', default='{}', help='Values to fill the service '
                       "request with in YAML format (e.g. '{a: 1, b: 2}'), otherwise the "
                       'service request will be published with default values')
    group.add_argument('--stdin', action='store_true', help='Read values from standard input')
    p.add_argument('-r', '--rate', metavar='N', type=float,
                   help='Repeat the call at a specific rate in Hz')
    p.set_defaults(main=call)


def _names_and_types(node: Any, include_hidden: bool) -> List[Any]:
    return api.visible(node.get_service_names_and_types(), include_hidden)


def list_services(args: Any) -> int:
    with direct.DirectNode(args) as node:
        services = _names_and_types(node, args.include_hidden_services)
    if args.count_services:
        print(len(services))
    else:
        for name, types in services:
            print(f'{name} [{", ".join(types)}]' if args.show_types else name)
    return 0


def service_type(args: Any) -> int:
    with direct.DirectNode(args) as node:
        types = direct.wait_for(node, lambda: dict(_names_and_types(
            node, args.include_hidden_services)).get(args.service_name))
    for t in types or ():
        print(t)
    return 0 if types else 1


def find(args: Any) -> int:
    with direct.DirectNode(args) as node:
        found = [n for n, t in _names_and_types(node, args.include_hidden_services)
                 if args.service_type in t]
    if args.count_services:
        print(len(found))
    elif found:
        print(*found, sep='\n')
    return 0


def call(args: Any) -> Any:
    if args.rate is not None and args.rate <= 0:
        raise RuntimeError('rate must be greater than zero')
    srv = api.interface_class(args.service_type, 'srv')
    text = sys.stdin.read() if args.stdin else args.values
    try:
        request = message_yaml.from_yaml(srv.Request, text)
    except ValueError as err:
        reason = str(err)
        return reason if reason.startswith('The passed') else f'Failed to populate field: {reason}'
    pkg, name = args.service_type.split('/')[0], args.service_type.split('/')[-1]
    with direct.DirectNode(args, node_name=f'{direct.NODE_NAME_PREFIX}_requester_{pkg}_{name}'
                           ) as node:
        client = node.create_client(srv, args.service_name)
        if not client.service_is_ready():
            print('waiting for service to become available...')
            while not client.wait_for_service(timeout_sec=1.0):
                pass
        while True:
            print(f'requester: making request: {request!r}\n')
            last = time.monotonic()
            future = client.call_async(request)
            node.executor.spin_until_future_complete(future)
            if future.result() is None:
                raise RuntimeError(f'Exception while calling service: {future.exception()!r}')
            print(f'response:\n{future.result()!r}\n')
            if args.rate is None:
                return 0
            time.sleep(max(0.0, last + 1.0 / args.rate - time.monotonic()))
