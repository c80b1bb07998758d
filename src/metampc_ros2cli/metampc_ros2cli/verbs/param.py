"""`ros2 param list|get|set|describe|dump|load`, as ros2param (Jazzy) prints them and exits.

Each verb talks to the node's parameter services: through the daemon's node, which knows the
graph already (:class:`DaemonParameterClient`, the calls of rclpy's AsyncParameterClient that
the verbs make), or with ``--no-daemon`` through an AsyncParameterClient of a node of the
verb's own, as ros2param's api does (its discovery of the services took 2.4-3.3 s under
LOCALHOST discovery). As in ros2param, a refused `set` (or a parameter of `load`) prints the node's
reason on stderr and still exits 0; a node that is not in the graph is the error line
``Node not found`` (exit 1), and parameter services that do not answer within 5 s end the verb
with ``Wait for service timed out waiting for parameter services for node NAME`` (exit 1;
`list` prints it and goes on with the other nodes).
"""
import math
import re
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from metampc_ros2cli import daemon, direct
from metampc_ros2cli.cli import add_family
from metampc_ros2cli.verbs.node import full_names

SERVICE_TIMEOUT_S = 5.0     # ros2param's wait for a node's parameter services
POLL_S = 0.1                # s between two questions to the daemon while waiting (ros2cli's)
# ros2param's labels of `get`, by rcl_interfaces/ParameterType value.
GET_LABELS = {1: 'Boolean value is:', 2: 'Integer value is:', 3: 'Double value is:',
              4: 'String value is:', 5: 'Byte values are:', 6: 'Boolean values are:',
              7: 'Integer values are:', 8: 'Double values are:', 9: 'String values are:'}
TYPE_NAMES = {0: 'not set', 1: 'boolean', 2: 'integer', 3: 'double', 4: 'string',
              5: 'byte array', 6: 'boolean array', 7: 'integer array', 8: 'double array',
              9: 'string array'}


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'param', 'Various param related sub-commands')

    p = verbs.add_parser('list', help='Output a list of available parameters')
    p.add_argument('node_name', nargs='?', help='Name of the ROS node')
    p.add_argument('--filter', nargs=1, help='Only parameters matching the regex expression '
                   'will be showed. Supports `re` regex syntax.')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    p.add_argument('--param-prefixes', nargs='+', default=[],
                   help='Only list parameters with the provided prefixes')
    p.add_argument('--param-type', action='store_true',
                   help='Print parameter types with parameter names')
    _common(p, timeout=False)
    p.set_defaults(main=list_params)

    p = verbs.add_parser('get', help='Get parameter')
    p.add_argument('node_name', help='Name of the ROS node')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    p.add_argument('parameter_name', help='Name of the parameter')
    p.add_argument('--hide-type', action='store_true', help='Hide the type information')
    _common(p)
    p.set_defaults(main=get)

    p = verbs.add_parser('set', help='Set parameter')
    p.add_argument('node_name', help='Name of the ROS node')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    p.add_argument('parameter_name', help='Name of the parameter')
    p.add_argument('value', help='Value of the parameter')
    _common(p)
    p.set_defaults(main=set_param)

    p = verbs.add_parser('describe', help='Show descriptive information about declared '
                         'parameters')
    p.add_argument('node_name', help='Name of the ROS node')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    p.add_argument('parameter_names', nargs='+', help='Names of the parameters')
    _common(p)
    p.set_defaults(main=describe)

    p = verbs.add_parser('dump', help='Show all of the parameters of a node in a YAML file '
                         'format')
    p.add_argument('node_name', help='Name of the ROS node')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    _common(p)
    p.set_defaults(main=dump)

    p = verbs.add_parser('load', help='Load parameter file for a node')
    p.add_argument('node_name', help='Name of the ROS node')
    p.add_argument('--include-hidden-nodes', action='store_true',
                   help='Consider hidden nodes as well')
    p.add_argument('parameter_file', help='Parameter file')
    p.add_argument('--no-use-wildcard', action='store_true',
                   help="Do not load parameters in the '/**' namespace into the node")
    _common(p)
    p.set_defaults(main=load)


def _common(parser: Any, timeout: bool = True) -> None:
    """ros2cli's node options (--spin-time, --use-sim-time, --no-daemon: no daemon here) and
    the verbs' --timeout."""
    direct.add_arguments(parser)
    daemon.add_arguments(parser)
    if timeout:
        parser.add_argument('--timeout', metavar='N', type=int, default=1,
                            help='Wait for N seconds until node becomes available (default '
                            '%(default)s sec)')


def _absolute(node_name: Optional[str]) -> Optional[str]:
    """ros2node's get_absolute_node_name: a leading '/' added."""
    if not node_name:
        return None
    return node_name if node_name.startswith('/') else '/' + node_name


def _wait_for(node: Any, found: Callable[[], Any], timeout: float) -> Any:
    """`found()` once true, or its last value after `timeout` s: the daemon's graph asked
    every POLL_S, a node of the verb's own spun (direct.wait_for)."""
    if not isinstance(node, daemon.GraphProxy):
        return direct.wait_for(node, found, timeout)
    end = time.monotonic() + timeout
    value = found()
    while not value and time.monotonic() < end:
        time.sleep(POLL_S)
        value = found()
    return value


def _node_found(node: Any, name: str, args: Any) -> bool:
    """ros2node's wait_for_node: `name` in the graph within --timeout s (negative: forever);
    a node of the verb's own gets at least direct's discovery grace (the daemon's graph is
    complete)."""
    timeout = math.inf if args.timeout < 0 else args.timeout
    if not isinstance(node, daemon.GraphProxy):
        timeout = max(timeout, direct.DISCOVERY_GRACE_S)
    return bool(_wait_for(node, lambda: name in full_names(node, args.include_hidden_nodes),
                          timeout))


class DaemonParameterClient:
    """The calls of rclpy's AsyncParameterClient that the verbs make, each made by the daemon's
    node (:func:`daemon.call_service`); the futures it returns are done, with the response, or
    with a TimeoutError when the service did not answer within SERVICE_TIMEOUT_S."""

    def __init__(self, node_name: str) -> None:
        self.node_name = node_name

    def ready(self, node: Any) -> bool:
        """The node's parameter services are in the graph within SERVICE_TIMEOUT_S."""
        wanted = f'{self.node_name}/get_parameters'
        return bool(_wait_for(node, lambda: wanted in dict(node.get_service_names_and_types()),
                              SERVICE_TIMEOUT_S))

    def _call(self, service: str, srv: Any, request: Any) -> Any:
        from rclpy.task import Future
        future = Future()
        response = daemon.call_service(f'{self.node_name}/{service}', srv, request,
                                       SERVICE_TIMEOUT_S)
        if response is None:
            future.set_exception(TimeoutError(f'no answer within {SERVICE_TIMEOUT_S:g} s'))
        else:
            future.set_result(response)
        return future

    def list_parameters(self, prefixes: Optional[List[str]] = None) -> Any:
        from rcl_interfaces.srv import ListParameters
        return self._call('list_parameters', ListParameters,
                          ListParameters.Request(prefixes=prefixes or []))

    def get_parameters(self, names: List[str]) -> Any:
        from rcl_interfaces.srv import GetParameters
        return self._call('get_parameters', GetParameters, GetParameters.Request(names=names))

    def set_parameters(self, parameters: List[Any]) -> Any:
        from rcl_interfaces.srv import SetParameters
        return self._call('set_parameters', SetParameters,
                          SetParameters.Request(parameters=parameters))

    def describe_parameters(self, names: List[str]) -> Any:
        from rcl_interfaces.srv import DescribeParameters
        return self._call('describe_parameters', DescribeParameters,
                          DescribeParameters.Request(names=names))


def _client(node: Any, node_name: str) -> Optional[Any]:
    """A parameter client of `node_name` whose services are there (the daemon's, or an
    AsyncParameterClient of the verb's own node), or None after SERVICE_TIMEOUT_S."""
    if isinstance(node, daemon.GraphProxy):
        client: Any = DaemonParameterClient(node_name)
        return client if client.ready(node) else None
    from rclpy.parameter_client import AsyncParameterClient
    client = AsyncParameterClient(node, node_name)
    return client if client.wait_for_services(timeout_sec=SERVICE_TIMEOUT_S) else None


def _ready_client(node: Any, node_name: str) -> Any:
    """:func:`_client`, or ros2param's RuntimeError (the verb's error line)."""
    client = _client(node, node_name)
    if client is None:
        raise RuntimeError('Wait for service timed out waiting for parameter services for '
                           f'node {node_name}')
    return client


def _response(node: Any, future: Any) -> Any:
    """The response of a parameter service call once done (None if it failed)."""
    if not isinstance(node, daemon.GraphProxy):
        direct.wait_future(node, future)
    return future.result() if future.exception() is None else None


def _result(node: Any, future: Any, node_name: str) -> Any:
    """The response of a parameter service call, or ros2param's RuntimeError."""
    response = _response(node, future)
    if response is None:
        raise RuntimeError(f'Exception while calling service of node {node_name}: '
                           f'{future.exception()}')
    return response


def _call(args: Any, request: Callable[[Any], Any]) -> Any:
    """The response of `request(client)` on the parameter services of ``args.node_name``.

    Raises:
        RuntimeError: 'Node not found', or as :func:`_ready_client` and :func:`_result`.
    """
    name = _absolute(args.node_name)
    with daemon.graph(args) as node:
        if not _node_found(node, name, args):
            raise RuntimeError('Node not found')
        return _result(node, request(_ready_client(node, name)), name)


def _sort_key(full_name: str) -> Tuple[str, str, str]:
    """ros2param sorts nodes as ros2node's NodeName tuples: (name, namespace, full name)."""
    namespace, _, name = full_name.rpartition('/')
    return name, namespace or '/', full_name


def _node_tuple(full_name: str) -> str:
    """How ros2param prints a node in `list`'s time-out line: its NodeName tuple."""
    name, namespace, full = _sort_key(full_name)
    return f'NodeName(name={name!r}, namespace={namespace!r}, full_name={full!r})'


def list_params(args: Any) -> Any:
    regex = re.compile(args.filter[0]) if args.filter is not None else None
    with daemon.graph(args) as node:
        wanted = _absolute(args.node_name)
        if wanted is not None:
            timeout = (0.0 if isinstance(node, daemon.GraphProxy)
                       else direct.DISCOVERY_GRACE_S)
            if not _wait_for(node, lambda: wanted in full_names(
                    node, args.include_hidden_nodes), timeout):
                return 'Node not found'
            names = [wanted]
        else:
            names = full_names(node, args.include_hidden_nodes)
        for name in sorted(set(names), key=_sort_key):
            client = _client(node, name)
            if client is None:
                print('Wait for service timed out waiting for parameter services for node '
                      + _node_tuple(name))
                continue
            future = client.list_parameters(prefixes=args.param_prefixes)
            if _response(node, future) is None:
                print(f"Exception while calling service of node '{name}': "
                      f'{future.exception()}', file=sys.stderr)
                continue
            listed = sorted(future.result().result.names)
            if regex is not None:
                listed = [n for n in listed if regex.match(n)]
            if not args.node_name and listed:
                print(f'{name}:')
            types: Dict[str, str] = {}
            if args.param_type:
                described = _result(node, client.describe_parameters(listed), name)
                types = {d.name: TYPE_NAMES[d.type] for d in described.descriptors}
            for n in listed:
                print(f'  {n} (type: {types[n]})' if args.param_type else f'  {n}')
    return 0


def get(args: Any) -> Any:
    response = _call(args, lambda client: client.get_parameters([args.parameter_name]))
    if not response.values:
        return 'Parameter not set'
    value = response.values[0]
    if value.type == 0:
        label, shown = 'Parameter not set.', None
    elif value.type in GET_LABELS:
        label = GET_LABELS[value.type]
        from rclpy.parameter import parameter_value_to_python
        shown = parameter_value_to_python(value)
    else:
        return f"Unknown parameter type '{value.type}'"
    if args.hide_type:
        print(shown)
    else:
        print(label, shown) if shown is not None else print(label)
    return 0


def describe(args: Any) -> Any:
    response = _call(args, lambda client: client.describe_parameters(args.parameter_names))
    for d in response.descriptors:
        print('Parameter name:', d.name)
        print('  Type:', TYPE_NAMES[d.type])
        if d.description:
            print('  Description:', d.description)
        print('  Constraints:')
        if d.read_only:
            print('    Read only: true')
        ranges = list(d.floating_point_range) + list(d.integer_range)
        if ranges:
            print('    Min value:', ranges[0].from_value)
            print('    Max value:', ranges[0].to_value)
            if ranges[0].step:
                print('    Step:', ranges[0].step)
        if d.additional_constraints:
            print('    Additional constraints:', d.additional_constraints)
    return 0


def set_param(args: Any) -> Any:
    from rcl_interfaces.msg import Parameter
    from rclpy.parameter import get_parameter_value
    parameter = Parameter(name=args.parameter_name,
                          value=get_parameter_value(string_value=args.value))
    response = _call(args, lambda client: client.set_parameters([parameter]))
    [result] = response.results
    if result.successful:
        print('Set parameter successful' + (f': {result.reason}' if result.reason else ''))
    else:
        print('Setting parameter failed' + (f': {result.reason}' if result.reason else ''),
              file=sys.stderr)
    return 0


def _insert(tree: Dict[str, Any], key: str, value: Any) -> None:
    """ros2param's dump nesting: 'a.b.c' -> {'a': {'b': {'c': value}}}."""
    head, dot, rest = key.partition('.')
    if dot:
        _insert(tree.setdefault(head, {}), rest, value)
    else:
        tree[key] = value


def dump(args: Any) -> Any:
    import yaml
    from rclpy.parameter import parameter_value_to_python
    name = _absolute(args.node_name)
    with daemon.graph(args) as node:
        if not _node_found(node, name, args):
            return 'Node not found'
        client = _client(node, name)
        if client is None:
            print('Wait for service timed out waiting for parameter services for node '
                  + name, file=sys.stderr)
            return 0
        future = client.list_parameters()
        if _response(node, future) is None:
            print(f"Exception while calling list_parameters service of node '{name}': "
                  f'{future.exception()}', file=sys.stderr)
            return 0
        names = sorted(future.result().result.names)
        response = _result(node, client.get_parameters(names), name)
    parameters: Dict[str, Any] = {}
    for n, value in zip(names, response.values):
        _insert(parameters, n, parameter_value_to_python(value))
    print(yaml.dump({name: {'ros__parameters': parameters}}, default_flow_style=False))
    return 0


def load(args: Any) -> Any:
    import yaml
    from rclpy.parameter import parameter_dict_from_yaml_file
    use_wildcard = not args.no_use_wildcard
    try:    # ros2param reads it after finding the node; an unreadable file is a traceback there
        parameters: List[Any] = list(parameter_dict_from_yaml_file(args.parameter_file,
                                                                   use_wildcard).values())
    except (OSError, yaml.YAMLError) as err:
        return f'Cannot read parameter file {args.parameter_file}: {err}'
    response = _call(args, lambda client: client.set_parameters(parameters))
    for parameter, result in zip(parameters, response.results):
        outcome = 'successful' if result.successful else 'failed'
        print(f'Set parameter {parameter.name} {outcome}'
              + (f': {result.reason}' if result.reason else ''),
              file=sys.stdout if result.successful else sys.stderr)
    return 0
