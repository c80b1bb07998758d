"""`ros2 topic list|info|type|find|echo|hz|bw|pub`, as ros2topic (Jazzy) prints and exits."""
import sys
import time
from typing import Any, Callable, Optional

from metampc_ros2cli import api, daemon, direct, message_yaml, names, rates
from metampc_ros2cli.cli import add_family

WAIT_POLL_S = 0.1


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'topic', 'Various topic related sub-commands')

    listing = names.add_verbs(verbs, 'topic', lambda node: node.get_topic_names_and_types(),
                              'rcl_interfaces/msg/Log')
    listing['list'].add_argument('-v', '--verbose', action='store_true',
                                 help='List full details about each topic')
    listing['list'].set_defaults(main=list_topics)

    p = verbs.add_parser('info', help='Print information about a topic')
    p.add_argument('topic_name', help="Name of the ROS topic to get info (e.g. '/chatter')")
    p.add_argument('-v', '--verbose', action='store_true',
                   help='Prints detailed information like the node name, node namespace, '
                   'topic type, GUID and QoS Profile of the publishers and subscribers')
    direct.add_arguments(p)
    daemon.add_arguments(p)
    p.set_defaults(main=info)

    p = verbs.add_parser('echo', help='Output messages from a topic')
    p.add_argument('topic_name', help="Name of the ROS topic to listen to (e.g. '/chatter')")
    p.add_argument('message_type', nargs='?', help="Type of the ROS message (e.g. "
                   "'std_msgs/msg/String')")
    api.add_qos_arguments(p, 'subscribe', 'sensor_data')
    p.add_argument('--csv', action='store_true',
                   help='Output all recursive fields separated by commas (e.g. for plotting)')
    p.add_argument('--field', default=None, help="Echo a selected field of a message. Use '.' "
                   'to select sub-fields (e.g. --field header.stamp)')
    p.add_argument('--full-length', '-f', action='store_true',
                   help='Output all elements for arrays, bytes, and strings')
    p.add_argument('--truncate-length', '-l', type=int,
                   default=message_yaml.DEFAULT_TRUNCATE_LENGTH,
                   help='The length to truncate arrays, bytes, and string to (default: '
                   f'{message_yaml.DEFAULT_TRUNCATE_LENGTH})')
    p.add_argument('--no-arr', action='store_true', help="Don't print array fields of messages")
    p.add_argument('--no-str', action='store_true', help="Don't print string fields of messages")
    p.add_argument('--flow-style', action='store_true', help='Print collections in the flow '
                   'style (not available with csv format)')
    p.add_argument('--no-lost-messages', action='store_true',
                   help="Don't report when a message is lost")
    p.add_argument('--raw', action='store_true', help='Echo the raw binary representation')
    p.add_argument('--filter', dest='filter_expr', help='Python expression to filter messages '
                   'that are printed. Expression can use Python builtins as well as m (the '
                   'message).')
    p.add_argument('--once', action='store_true',
                   help='Print the first message received and then exit.')
    p.add_argument('--timeout', metavar='N', type=api.positive_float, default=None,
                   help='Set a timeout in seconds for waiting')
    p.add_argument('--include-message-info', '-i', action='store_true',
                   help='Shows the associated message info.')
    direct.add_arguments(p)
    p.set_defaults(main=echo)

    p = verbs.add_parser('hz', help='Print the average publishing rate to screen')
    p.add_argument('topic_name', help="Name of the ROS topic to listen to (e.g. '/chatter')")
    p.add_argument('--window', '-w', dest='window_size', type=int, default=rates.HZ_WINDOW,
                   metavar='WINDOW', help='window size, in # of messages, for calculating rate '
                   f'(default: {rates.HZ_WINDOW})')
    p.add_argument('--filter', dest='filter_expr', default=None, metavar='EXPR',
                   help='only measure messages matching the specified Python expression')
    p.add_argument('--wall-time', dest='use_wtime', action='store_true',
                   help='calculates rate using wall time which can be helpful when clock is '
                   'not published during simulation')
    direct.add_arguments(p)
    p.set_defaults(main=hz)

    p = verbs.add_parser('bw', help='Display bandwidth used by topic')
    p.add_argument('topic_name', help="Name of the ROS topic to listen to (e.g. '/chatter')")
    p.add_argument('--window', '-w', type=int, default=rates.BW_WINDOW,
                   help=f'maximum window size, in # of messages, for calculating rate '
                   f'(default: {rates.BW_WINDOW})')
    direct.add_arguments(p)
    p.set_defaults(main=bw)

    p = verbs.add_parser('pub', help='Publish a message to a topic')
    p.add_argument('topic_name', help="Name of the ROS topic to publish to (e.g. '/chatter')")
    p.add_argument('message_type', help="Type of the ROS message (e.g. 'std_msgs/String')")
    group = p.add_mutually_exclusive_group()
    group.add_argument('values', nargs='?', default='{}', help='Values to fill the message '
                       "with in YAML format (e.g. 'data: Hello World'), otherwise the message "
                       'will be published with default values')
    group.add_argument('--stdin', action='store_true', help='Read values from standard input')
    p.add_argument('-r', '--rate', metavar='N', type=api.positive_float, default=1.0,
                   help='Publishing rate in Hz (default: 1)')
    p.add_argument('-p', '--print', metavar='N', type=int, default=1,
                   help='Only print every N-th published message (default: 1)')
    group = p.add_mutually_exclusive_group()
    group.add_argument('-1', '--once', action='store_true', help='Publish one message and exit')
    group.add_argument('-t', '--times', type=int, default=0,
                       help='Publish this number of times and then exit')
    p.add_argument('-w', '--wait-matching-subscriptions', type=int, default=None,
                   help='Wait until finding the specified number of matching subscriptions. '
                   'Defaults to 1 when using "-1"/"--once"/"--times", otherwise defaults to 0.')
    p.add_argument('--max-wait-time-secs', type=api.positive_float, default=None,
                   help='The maximum wait time in seconds for the matching subscriptions')
    p.add_argument('--keep-alive', metavar='N', type=api.positive_float, default=0.1,
                   help='Keep publishing node alive for N seconds after the last msg '
                   '(default: 0.1)')
    p.add_argument('-n', '--node-name', help='Name of the created publishing node')
    api.add_qos_arguments(p, 'publish', 'default')
    direct.add_arguments(p)
    p.set_defaults(main=pub)


def list_topics(args: Any) -> int:
    if not args.verbose:
        return names.list_names(lambda node: node.get_topic_names_and_types(), args)
    with daemon.graph(args) as node:
        counts = [(n, t, node.count_publishers(n), node.count_subscribers(n))
                  for n, t in api.visible(node.get_topic_names_and_types(),
                                          args.include_hidden)]
    if args.count:
        print(len(counts))
        return 0
    for side, index in (('Published', 2), ('Subscribed', 3)):
        lines = [f'{side} topics:']
        for row in counts:
            if row[index]:
                what = 'publisher' if index == 2 else 'subscriber'
                plural = 's' if row[index] > 1 else ''
                lines.append(f' * {row[0]} [{", ".join(row[1])}] {row[index]} {what}{plural}')
        print('\n'.join(lines) + '\n')
    return 0


def info(args: Any) -> Any:
    """From the daemon's graph, as ros2cli's (a verb's own node, under LOCALHOST discovery,
    counted 0 publishers of a topic at 10 Hz in 9 of 13 calls)."""
    with daemon.graph(args) as node:
        name = api.expand(node, args.topic_name)
        types = dict(node.get_topic_names_and_types()).get(name)
        if types is None and not isinstance(node, daemon.GraphProxy):
            types = direct.wait_for(node, lambda: dict(node.get_topic_names_and_types()).get(name))
        if types is None:
            return f"Unknown topic '{args.topic_name}'"
        end = '\n\n' if args.verbose else '\n'
        print(f'Type: {types[0] if len(types) == 1 else types}', end=end)
        print(f'Publisher count: {node.count_publishers(name)}', end=end)
        if args.verbose:
            for endpoint in node.get_publishers_info_by_topic(name):
                print(endpoint, end=end)
        print(f'Subscription count: {node.count_subscribers(name)}', end=end)
        if args.verbose:
            for endpoint in node.get_subscriptions_info_by_topic(name):
                print(endpoint, end=end)
    return 0


def _message_class(node: Any, name: str, given: Optional[str], wait: bool) -> Any:
    """The class of `given`, else of the topic's one type in the graph (waiting for it to be
    published when `wait`, as hz and bw do); RuntimeError if it cannot be determined."""
    if given is not None:
        return api.interface_class(given, 'msg')
    warned = False
    while True:
        types = direct.wait_for(node, lambda: dict(node.get_topic_names_and_types()).get(name))
        if types:
            if len(types) > 1:
                raise RuntimeError(f"Cannot echo topic '{name}', as it contains more than one "
                                   f"type: [{', '.join(types)}]")
            try:
                return api.interface_class(types[0], 'msg')
            except RuntimeError:
                raise RuntimeError(f"The message type '{types[0]}' is invalid") from None
        if not warned:
            print(f'WARNING: topic [{name}] does not appear to be published yet')
            warned = True
        if not wait:
            raise RuntimeError('Could not determine the type for the passed topic')
        node.executor.spin_once(timeout_sec=WAIT_POLL_S)


def _filter(expr: Optional[str]) -> Optional[Callable[[Any], bool]]:
    if not expr:
        return None
    code = compile(expr, '<filter>', 'eval')
    return lambda m: bool(eval(code, {}, {'m': m}))


def _spin(node: Any, done: Callable[[], bool], timeout: Optional[float] = None) -> None:
    """Spin the verb's node until `done()` or `timeout` s of wall time."""
    end = None if timeout is None else time.monotonic() + timeout
    while not done():
        left = None if end is None else end - time.monotonic()
        if left is not None and left <= 0:
            return
        node.executor.spin_once(timeout_sec=0.1 if left is None else min(left, 0.1))


def echo(args: Any) -> Any:
    field = None
    if args.field is not None:
        field = [f for f in args.field.split('.') if f]
        if not field:
            return f"Invalid field value '{args.field}'"
    keep = _filter(args.filter_expr)
    limit = None if args.full_length else args.truncate_length
    printed = []

    def show(msg: Any, msg_info: Any = None) -> None:
        sub = msg
        for name in field or ():
            try:
                sub = getattr(sub, name)
            except AttributeError as err:
                raise RuntimeError(f"Invalid field '{'.'.join(field)}': {err}") from None
        if keep is not None and not keep(sub):
            return
        printed.append(True)
        if not hasattr(sub, '__slots__'):
            if args.include_message_info:
                print(f'---Got new message, message info:---\n{msg_info}\n---Message data:---')
            print(sub, end='\n---\n')
        elif args.csv:
            line = message_yaml.to_csv(sub, truncate_length=limit, no_arr=args.no_arr,
                                       no_str=args.no_str)
            if args.include_message_info:
                line = ','.join(str(v) for v in msg_info.values()) + ',' + line
            print(line)
        else:
            if args.include_message_info:
                import yaml
                print(yaml.dump(dict(msg_info)), end='---\n')
            print(message_yaml.to_yaml(sub, truncate_length=limit, no_arr=args.no_arr,
                                       no_str=args.no_str, flow_style=args.flow_style),
                  end='---\n')

    with direct.DirectNode(args) as node:
        name = api.expand(node, args.topic_name)
        cls = _message_class(node, name, args.message_type, wait=False)
        qos = api.qos_from_args(args, node.get_publishers_info_by_topic(name))
        node.create_subscription(cls, name, show, qos, raw=args.raw,
                                 event_callbacks=None if args.no_lost_messages else _lost(node))
        if args.once:
            _spin(node, lambda: bool(printed), args.timeout)
        else:
            _spin(node, lambda: False, args.timeout)
    return 0


def _lost(node: Any) -> Any:
    from rclpy.event_handler import SubscriptionEventCallbacks

    def report(status: Any) -> None:
        print(f'A message was lost!!!\n\ttotal count change:{status.total_count_change}'
              f'\n\ttotal count: {status.total_count}', end='---\n')
    return SubscriptionEventCallbacks(message_lost=report)


def _now_ns(node: Any, wall: bool) -> int:
    return time.time_ns() if wall else node.get_clock().now().nanoseconds


def hz(args: Any) -> int:
    keep = _filter(args.filter_expr)
    window = rates.RateWindow(args.window_size)
    with direct.DirectNode(args) as node:
        from rclpy.qos import qos_profile_sensor_data
        name = api.expand(node, args.topic_name)
        cls = _message_class(node, name, None, wait=True)

        def tick(msg: Any) -> None:
            if keep is None or keep(msg):
                line = window.add(_now_ns(node, args.use_wtime))
                if line:
                    print(line)
        node.create_subscription(cls, name, tick, qos_profile_sensor_data)
        _spin(node, lambda: False)
    return 0


def bw(args: Any) -> int:
    window = rates.BandwidthWindow(args.window)
    with direct.DirectNode(args) as node:
        from rclpy.qos import qos_profile_sensor_data
        name = api.expand(node, args.topic_name)
        cls = _message_class(node, name, None, wait=True)
        node.create_subscription(cls, name, lambda data: window.add(_now_ns(node, False),
                                                                    len(data)),
                                 qos_profile_sensor_data, raw=True)
        print(f'Subscribed to [{name}]')

        def report() -> None:
            line = window.report(_now_ns(node, False))
            if line:
                print(line)
        node.create_timer(1.0, report)
        _spin(node, lambda: False)
    return 0


def pub(args: Any) -> Any:
    times = 1 if args.once else args.times
    if times < 0:
        return 'Value must be positive or zero'
    wait_for = (args.wait_matching_subscriptions if args.wait_matching_subscriptions is not None
                else int(times != 0))
    if wait_for == 0 and args.max_wait_time_secs is not None:
        return ('--max-wait-time-secs option is only effective with '
                '--wait-matching-subscriptions, --once or --times')
    cls = api.interface_class(args.message_type, 'msg')
    text = sys.stdin.read() if args.stdin else args.values
    stamps: list = []       # `header: auto` and `stamp: now`, stamped at each publish
    try:
        msg = message_yaml.from_yaml(cls, text, stamps)
    except ValueError as err:
        reason = str(err)
        return reason if reason.startswith('The passed') else f'Failed to populate field: {reason}'
    with direct.DirectNode(args, node_name=args.node_name or '') as node:
        publisher = node.create_publisher(cls, api.expand(node, args.topic_name),
                                          api.qos_from_args(args))
        waited, printed_wait = 0.0, False
        while publisher.get_subscription_count() < wait_for:
            if not printed_wait:
                print(f'Waiting for at least {wait_for} matching subscription(s)...')
                printed_wait = True
            if args.max_wait_time_secs is not None and waited >= args.max_wait_time_secs:
                return (f'Timed out waiting for subscribers: Expected {wait_for} subcribers but '
                        f'only got {publisher.get_subscription_count()} subscribers')
            node.executor.spin_once(timeout_sec=WAIT_POLL_S)
            waited += WAIT_POLL_S
        print('publisher: beginning loop')
        count = 0
        period = 1.0 / args.rate
        next_at = time.monotonic()
        while True:
            count += 1
            now = node.get_clock().now().to_msg()
            for owner, attr in stamps:
                setattr(owner, attr, now)
            if args.print and count % args.print == 0:
                print(f'publishing #{count}: {msg!r}\n')
            publisher.publish(msg)
            if times and count >= times:
                break
            next_at += period
            _spin(node, lambda: time.monotonic() >= next_at, max(0.0, next_at - time.monotonic()))
        time.sleep(args.keep_alive)
    return 0
