"""`ros2 service list|type|find|call`, as ros2service (Jazzy) prints and exits."""
import sys
import time
from typing import Any

from metampc_ros2cli import api, direct, message_yaml, names
from metampc_ros2cli.cli import add_family


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'service', 'Various service related sub-commands')

    names.add_verbs(verbs, 'service', lambda node: node.get_service_names_and_types(),
                    'rcl_interfaces/srv/ListParameters')

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
        client = node.create_client(srv, api.expand(node, args.service_name))
        if not client.service_is_ready():
            print('waiting for service to become available...')
            while not client.wait_for_service(timeout_sec=1.0):
                pass
        while True:
            print(f'requester: making request: {request!r}\n')
            last = time.monotonic()
            future = client.call_async(request)
            direct.wait_future(node, future)
            if future.result() is None:
                raise RuntimeError(f'Exception while calling service: {future.exception()!r}')
            print(f'response:\n{future.result()!r}\n')
            if args.rate is None:
                return 0
            time.sleep(max(0.0, last + 1.0 / args.rate - time.monotonic()))
