"""What several verb families share: hidden names, interface classes by name, QoS options."""
import argparse
from typing import Any, List, Tuple


def is_hidden(name: str) -> bool:
    """A topic or service name with a token starting with '_' (ros2cli hides those)."""
    return any(token.startswith('_') for token in name.split('/'))


def visible(names_and_types: List[Tuple[str, List[str]]],
            include_hidden: bool) -> List[Tuple[str, List[str]]]:
    """The (name, types) pairs that a listing shows."""
    return [(n, t) for n, t in names_and_types if include_hidden or not is_hidden(n)]


def expand(node: Any, name: str) -> str:
    """A topic or service name as given on the command line, made absolute ('y' -> '/y')."""
    from rclpy.expand_topic_name import expand_topic_name
    try:
        return expand_topic_name(name, node.get_name(), node.get_namespace())
    except ValueError as err:
        raise RuntimeError(str(err)) from None


def interface_class(type_name: str, kind: str) -> Any:
    """The Python class of 'pkg/msg/Type' or 'pkg/Type' (`kind` 'msg' or 'srv').

    Raises:
        RuntimeError: not the full name of an interface of that kind that is installed.
    """
    from metampc_common.message_types import message_class
    parts = type_name.split('/')
    if len(parts) == 2:
        parts.insert(1, kind)
    try:
        if len(parts) != 3 or parts[1] != kind:
            raise ValueError(type_name)
        cls = message_class('/'.join(parts))
    except (AttributeError, ImportError, ValueError):
        raise RuntimeError(f'The passed {"message" if kind == "msg" else "service"} type is '
                           'invalid') from None
    if kind == 'srv' and not hasattr(cls, 'Request'):
        raise RuntimeError('The passed service type is invalid')
    return cls


def positive_float(text: str) -> float:
    """argparse type: a float > 0."""
    value = float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f'{text} is not a positive number')
    return value


class QosKeys:
    """The short keys of an rclpy.qos enum (`name`) as argparse choices, read when first
    asked (a value given, the help): building the `ros2` parser imports no rclpy (0.1 s of an
    idle start, more on a loaded machine)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def keys(self) -> List[str]:
        import rclpy.qos
        return list(getattr(rclpy.qos, self.name).short_keys())

    def __contains__(self, value: Any) -> bool:
        return value in self.keys()

    def __iter__(self) -> Any:
        return iter(self.keys())


def add_qos_arguments(parser: argparse.ArgumentParser, verb: str, default: str) -> None:
    """ros2cli's --qos-* options (profile, depth, history, reliability, durability); the
    choices are listed in each help (a metavar keeps argparse from reading them at once)."""
    parser.add_argument('--qos-profile', choices=QosKeys('QoSPresetProfiles'),
                        metavar='PROFILE', default=default,
                        help=f'Quality of service preset profile to {verb} with: %(choices)s '
                        f'(default: {default})')
    parser.add_argument('--qos-depth', metavar='N', type=int,
                        help=f'Queue size setting to {verb} with (overrides depth value of '
                        '--qos-profile option)')
    parser.add_argument('--qos-history', choices=QosKeys('QoSHistoryPolicy'), metavar='HISTORY',
                        help=f'History of samples setting to {verb} with: %(choices)s')
    parser.add_argument('--qos-reliability', choices=QosKeys('QoSReliabilityPolicy'),
                        metavar='RELIABILITY', help=f'Quality of service reliability setting '
                        f'to {verb} with: %(choices)s (default: compatible with the running '
                        'endpoints)')
    parser.add_argument('--qos-durability', choices=QosKeys('QoSDurabilityPolicy'),
                        metavar='DURABILITY', help=f'Quality of service durability setting '
                        f'to {verb} with: %(choices)s (default: compatible with the running '
                        'endpoints)')


def qos_from_args(args: argparse.Namespace, publishers: List[Any] = ()) -> Any:
    """The profile the options ask for; reliability and durability that are not given are
    those every publisher offers, else best effort / volatile (as ros2 topic echo)."""
    from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSPresetProfiles,
                           QoSReliabilityPolicy)
    profile = QoSPresetProfiles.get_from_short_key(args.qos_profile)
    if args.qos_depth is not None:
        profile.depth = args.qos_depth
    if args.qos_history is not None:
        profile.history = QoSHistoryPolicy.get_from_short_key(args.qos_history)
    offered = [p.qos_profile for p in publishers]
    if args.qos_reliability is not None:
        profile.reliability = QoSReliabilityPolicy.get_from_short_key(args.qos_reliability)
    elif offered:
        reliable = all(p.reliability == QoSReliabilityPolicy.RELIABLE for p in offered)
        profile.reliability = (QoSReliabilityPolicy.RELIABLE if reliable
                               else QoSReliabilityPolicy.BEST_EFFORT)
    if args.qos_durability is not None:
        profile.durability = QoSDurabilityPolicy.get_from_short_key(args.qos_durability)
    elif offered:
        latched = all(p.durability == QoSDurabilityPolicy.TRANSIENT_LOCAL for p in offered)
        profile.durability = (QoSDurabilityPolicy.TRANSIENT_LOCAL if latched
                              else QoSDurabilityPolicy.VOLATILE)
    return profile
