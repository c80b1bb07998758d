"""`ros2 bag info|play|record`, with ros2bag's (Jazzy) syntax, on this project's MCAP code.

``record`` runs the project's recorder node in this process and makes a rosbag2 bag folder
(``-o NAME``, default ``rosbag2_YYYY_MM_DD-HH_MM_SS``: ``NAME_0.mcap`` and, once Ctrl-C has
finished the file, ``metadata.yaml``); ``info`` prints what rosbag2's prints
(:mod:`metampc_ros2cli.bag_info`) for a bag folder or an MCAP file; ``play`` republishes one
with :mod:`metampc_recording.player`. Errors are one line and a non-zero status, as ros2bag's:
a bag path that does not exist is an argparse error (status 2); the others (not a bag, cut
short, unknown topic, an output folder that exists) status 1. See docs/recording.md.
"""
import argparse
import datetime
import os
import sys
from typing import Any

from metampc_ros2cli.cli import add_family

STORAGE_IDS = ('mcap',)


def print_error(text: str) -> str:
    """ros2bag's error line (returned: the CLI prints it to stderr, status 1)."""
    return f'[ERROR] [ros2bag]: {text}'


def print_warn(text: str) -> str:
    return f'[WARN] [ros2bag]: {text}'


def bag_path(args: Any) -> str:
    """The verb's bag path; one that does not exist is the argparse error of ros2bag's
    check_path_exists (usage, error line, status 2), raised when the verb runs, so that a
    command line parses without the bag (the docs' lines are checked so)."""
    if not os.path.exists(args.bag_path):
        args.bag_parser.error(f"argument bag_path: Bag path '{args.bag_path}' does not exist!")
    return args.bag_path


def check_positive_float(value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{value} is not the valid type (float)') from None
    if number <= 0:
        raise argparse.ArgumentTypeError(f'{value} is not in the valid range (> 0.0)')
    return number


def check_not_negative_float(value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{value} is not the valid type (float)') from None
    if number < 0:
        raise argparse.ArgumentTypeError(f'Value {value} is less than zero.')
    return number


def _add_reader_arguments(parser: argparse.ArgumentParser) -> None:
    """ros2bag's add_standard_reader_args."""
    parser.add_argument('bag_path', help='Bag to open')
    parser.set_defaults(bag_parser=parser)
    parser.add_argument('-s', '--storage', default='', choices=STORAGE_IDS,
                        help='Storage implementation of bag. By default attempts to detect '
                        'automatically - use this argument to override.')


def add_parser(subparsers: Any) -> None:
    verbs = add_family(subparsers, 'bag', 'Various bag related sub-commands')

    p = verbs.add_parser('info', help='Print information about a bag to the screen')
    _add_reader_arguments(p)
    p.add_argument('-t', '--topic-name', action='store_true', help='Only display topic names.')
    p.add_argument('-v', '--verbose', action='store_true',
                   help='Display request/response information for services')
    p.set_defaults(main=info)

    p = verbs.add_parser('play', help='Play back ROS data from a bag')
    _add_reader_arguments(p)
    p.add_argument('-r', '--rate', type=check_positive_float, default=1.0,
                   help='rate at which to play back messages. Valid range > 0.0.')
    p.add_argument('--topics', type=str, default=[], metavar='topic', nargs='+',
                   help='Space-delimited list of topics to play.')
    p.add_argument('-l', '--loop', action='store_true',
                   help='enables loop playback when playing a bagfile: it starts back at the '
                   'beginning on reaching the end and plays indefinitely.')
    p.add_argument('-d', '--delay', type=check_not_negative_float, default=0.0,
                   help='Sleep duration before play (each loop), in seconds. Negative '
                   'durations invalid.')
    p.add_argument('--start-offset', type=check_not_negative_float, default=0.0,
                   help='Start the playback player this many seconds into the bag file.')
    p.add_argument('--wait-subscribers', type=check_not_negative_float, default=0.0,
                   metavar='SECONDS',
                   help='(not in rosbag2) after the delay, wait up to SECONDS until every '
                   'volatile topic played has a subscriber, and as long until its first '
                   'message is acknowledged')
    p.set_defaults(main=play)

    p = verbs.add_parser('record', help='Record ROS data to a bag')
    p.add_argument('-o', '--output', help='Destination of the bagfile to create, defaults to a '
                   'timestamped folder in the current directory.')
    p.add_argument('-s', '--storage', default='mcap', choices=STORAGE_IDS,
                   help="Storage identifier to be used, defaults to '%(default)s'.")
    topics = p.add_mutually_exclusive_group()
    topics.add_argument('topics_positional', type=str, default=[], metavar='[Topic ...]',
                        nargs='*', help='Space-delimited list of topics to record. (deprecated)')
    topics.add_argument('--topics', type=str, default=[], metavar='Topic', nargs='+',
                        help='Space-delimited list of topics to record.')
    p.add_argument('-a', '--all', action='store_true',
                   help='Record all topics: those the recorder takes when its topics '
                   'parameter is empty (docs/recording.md).')
    p.add_argument('--all-topics', action='store_true', help='The same as --all here.')
    p.add_argument('-p', '--polling-interval', type=int, default=100,
                   help='Time in ms to wait between querying available topics for recording.')
    p.add_argument('--use-sim-time', action='store_true',
                   help='Use simulation time (/clock) for message timestamps.')
    p.add_argument('--node-name', type=str, default='rosbag2_recorder',
                   help='Specify the recorder node name. Default is %(default)s.')
    p.set_defaults(main=record)


def info(args: Any) -> int:
    from metampc_ros2cli.bag_info import (count_service_requests, format_bag_metadata,
                                          format_service_info, is_service_event_topic,
                                          read_bag_info)
    if args.topic_name and args.verbose:
        print("Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter "
              'will be ignored.')
    bag = read_bag_info(bag_path(args))
    if bag.scanned:
        print(print_warn(f'{bag.files[0]} has no summary (an unfinished recording): its '
                         'complete records were counted'), file=sys.stderr)
    if args.verbose:
        sys.stdout.write(format_bag_metadata(bag, only_topic=True)
                         + format_service_info(count_service_requests(bag)) + '\n')
    elif args.topic_name:
        for topic in bag.topics_with_message_count:
            if not is_service_event_topic(topic.name, topic.type):
                print(topic.name)
    else:
        print(format_bag_metadata(bag))
    return 0


def play(args: Any) -> int:
    from metampc_recording.player import PlayConfig, run_player
    from metampc_ros2cli.bag_info import read_bag_info
    bag = read_bag_info(bag_path(args))
    if bag.storage_identifier != 'mcap':
        raise RuntimeError(f'storage {bag.storage_identifier!r} cannot be played here (mcap '
                           'only)')
    if len(bag.files) != 1:
        raise RuntimeError(f'{args.bag_path} has {len(bag.files)} files; only a bag of one '
                           'file is played here')
    config = PlayConfig(rate=args.rate, delay=args.delay, topics=args.topics,
                        wait_for_subscribers=args.wait_subscribers,
                        start_offset=args.start_offset, loop=args.loop)
    try:
        run_player(bag.files[0], config)     # returns at the end, or at Ctrl-C
    except (OSError, ValueError) as err:     # a file metadata.yaml lists is missing; a topic
        raise RuntimeError(str(err)) from None
    return 0


def record(args: Any) -> Any:
    from metampc_common.ros_args import ros_args
    from metampc_recording.main import recorder
    from metampc_recording.mcap_writer import bag_folder_file, write_bag_metadata_file
    from metampc_recording.recorder_config import RecorderConfig
    from metampc_ros2cli.bag_info import stored_bag_metadata
    from rclpy.exceptions import InvalidNodeNameException
    from rclpy.validate_node_name import validate_node_name
    uri = args.output or datetime.datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
    topics = args.topics or args.topics_positional
    every = args.all or args.all_topics
    if not (every or topics):
        return print_error('Need to specify at least one option out of --all, --all-topics '
                           'or --topics')
    if every and topics:
        print(print_warn('--all or --all-topics will override --topics'))
    try:
        validate_node_name(args.node_name)
    except InvalidNodeNameException as err:
        return print_error(f"{str(err).splitlines()[0]} '{args.node_name}'")
    if os.path.isdir(uri):
        return print_error(f"Output folder '{uri}' already exists.")
    if os.path.exists(uri):
        return print_error(f'Failed to create bag directory ({uri}).')
    config = RecorderConfig(output=bag_folder_file(uri), topics=() if every else topics,
                            discovery_period=args.polling_interval / 1000)
    params = config.to_parameters()
    if args.use_sim_time:
        params['use_sim_time'] = True
    rc = recorder(ros_args(params, name=args.node_name))    # until Ctrl-C
    if rc == 0 and os.path.isfile(config.output):
        write_bag_metadata_file(uri, stored_bag_metadata(config.output))
    if os.path.isdir(uri) and not os.listdir(uri):
        os.rmdir(uri)
    return rc
