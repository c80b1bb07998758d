"""Which topics of the graph a recorder or a live view takes, found as they appear.

Shared by the recorder and the Foxglove live view (node side: it calls the node's graph
queries). A topic is taken once it has a publisher, because the subscription's QoS follows the
publishers' (:func:`metampc_recording.rosbag2_qos.request_for_offers`).
"""
from typing import Callable, Collection, Iterable, Iterator, List, NamedTuple, Set

from metampc_common.params import ParameterError
from metampc_recording.rclpy_adapters import qos_from_rclpy
from metampc_recording.rosbag2_qos import QosProfile
from rclpy.node import Node

SYSTEM_TOPICS = frozenset({'/rosout', '/parameter_events'})


class NewTopic(NamedTuple):
    """A selected topic seen with a publisher for the first time."""

    name: str
    type_name: str                  # 'pkg/msg/Type'
    offered: List[QosProfile]       # one per publisher
    type_hash: str                  # 'RIHS01_...' of the first publisher


def resolve_topics(node: Node, names: Iterable[str]) -> Set[str]:
    """Fully qualified names of `names` in the node's namespace.

    Raises:
        ParameterError: a name that is not a valid topic name.
    """
    try:
        return {node.resolve_topic_name(name) for name in names}
    except RuntimeError as err:    # rclpy's RCLError
        raise ParameterError(f'bad topic name in topics: {err}') from None


def default_topic(topic: str, namespace: str, clock: bool = False) -> bool:
    """Whether `topic` is taken when no list is given: a topic under `namespace`, except
    /rosout, /parameter_events, hidden topics (a `_` token) and, unless `clock`, /clock."""
    if topic in SYSTEM_TOPICS or (topic == '/clock' and not clock):
        return False
    if any(token.startswith('_') for token in topic.split('/')):
        return False
    namespace = namespace.rstrip('/')
    return not namespace or topic.startswith(namespace + '/')


def new_topics(node: Node, known: Collection[str], selected: Callable[[str], bool],
               skip: Callable[[str, str], None]) -> Iterator[NewTopic]:
    """The topics of the graph that are `selected`, not `known` and have a publisher.

    A selected topic with several types goes to ``skip(topic, reason)`` instead (which should
    make it known, so that it is reported once); a topic seen only through subscriptions is
    left for a later call.
    """
    for topic, types in node.get_topic_names_and_types():
        if topic in known or not selected(topic):
            continue
        if len(types) != 1:
            skip(topic, f'several types {types}')
            continue
        publishers = node.get_publishers_info_by_topic(topic)
        if publishers:
            yield NewTopic(topic, types[0], [qos_from_rclpy(p.qos_profile) for p in publishers],
                           str(publishers[0].topic_type_hash))
