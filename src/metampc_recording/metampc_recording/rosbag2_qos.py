"""QoS profiles in rosbag2's YAML form, and rosbag2's rules for choosing QoS from them.

Reads and writes the ``offered_qos_profiles`` channel metadata of rosbag2 (Jazzy, metadata
version 9: one map per publisher, policies as lower-case strings, durations as ``{sec, nsec}``)
and picks QoS as rosbag2 does: recording (:func:`request_for_offers`) subscribes reliable /
transient_local only if every publisher is; playback (:func:`offer_for_recorded`) offers the
recorded profile when the recorded publishers agree, history keep_last 10, else the default.
Plain data only: the recorder and player nodes convert to and from rclpy's QoSProfile. The
format with an example: docs/recording.md.
"""
from dataclasses import dataclass, replace
from typing import List, Sequence

import yaml

INFINITE_NS = 2 ** 63 - 1
DEFAULT_DEPTH = 10   # rmw_qos_profile_default.depth


@dataclass(frozen=True)
class QosProfile:
    """One QoS profile; policy names as rosbag2 writes them, durations in ns."""

    history: str = 'keep_last'
    depth: int = DEFAULT_DEPTH
    reliability: str = 'reliable'
    durability: str = 'volatile'
    deadline_ns: int = INFINITE_NS
    lifespan_ns: int = INFINITE_NS
    liveliness: str = 'system_default'
    liveliness_lease_duration_ns: int = INFINITE_NS
    avoid_ros_namespace_conventions: bool = False


def _duration(ns: int) -> dict:
    return {'sec': ns // 1_000_000_000, 'nsec': ns % 1_000_000_000}


def _nanoseconds(node: dict) -> int:
    return int(node['sec']) * 1_000_000_000 + int(node['nsec'])


def profiles_to_yaml(profiles: Sequence[QosProfile]) -> str:
    """rosbag2's ``offered_qos_profiles`` text for a list of profiles ('[]' when empty)."""
    if not profiles:
        return '[]'
    items = [{
        'history': p.history,
        'depth': p.depth,
        'reliability': p.reliability,
        'durability': p.durability,
        'deadline': _duration(p.deadline_ns),
        'lifespan': _duration(p.lifespan_ns),
        'liveliness': p.liveliness,
        'liveliness_lease_duration': _duration(p.liveliness_lease_duration_ns),
        'avoid_ros_namespace_conventions': p.avoid_ros_namespace_conventions,
    } for p in profiles]
    return yaml.safe_dump(items, sort_keys=False, default_flow_style=False)


def profiles_to_dicts(profiles: Sequence[QosProfile]) -> list:
    """The same profiles as YAML-ready data (for the bag metadata, where they are a sequence)."""
    return yaml.safe_load(profiles_to_yaml(profiles))


def profiles_from_yaml(text: str) -> List[QosProfile]:
    """Parse ``offered_qos_profiles``; ValueError if it is not a list of complete profiles.

    Integers for the policies (rosbag2 metadata before version 9) are not accepted: this
    project only reads what it writes and what Jazzy writes.
    """
    items = yaml.safe_load(text) if text else []
    if not isinstance(items, list):
        raise ValueError('offered_qos_profiles is not a YAML sequence')
    try:
        return [QosProfile(
            history=str(i['history']), depth=int(i['depth']),
            reliability=str(i['reliability']), durability=str(i['durability']),
            deadline_ns=_nanoseconds(i['deadline']), lifespan_ns=_nanoseconds(i['lifespan']),
            liveliness=str(i['liveliness']),
            liveliness_lease_duration_ns=_nanoseconds(i['liveliness_lease_duration']),
            avoid_ros_namespace_conventions=bool(i['avoid_ros_namespace_conventions']),
        ) for i in items]
    except (KeyError, TypeError) as err:
        raise ValueError(f'incomplete QoS profile in offered_qos_profiles: {err}') from None


def request_for_offers(offers: Sequence[QosProfile], depth: int) -> QosProfile:
    """QoS for a recording subscription that matches every publisher in `offers`.

    Args:
        offers: the publishers' profiles (may be empty: then the defaults, reliable + volatile).
        depth: keep_last depth of the subscription queue; 0: keep_all (every received
            sample stays until it is taken; a full reader acknowledges no more until then, so
            a publisher that waits for its acknowledgements, metampc_common.held_publisher,
            loses none).
    """
    reliable = all(p.reliability == 'reliable' for p in offers)
    latched = bool(offers) and all(p.durability == 'transient_local' for p in offers)
    return QosProfile(history='keep_last' if depth else 'keep_all', depth=depth,
                      reliability='reliable' if reliable else 'best_effort',
                      durability='transient_local' if latched else 'volatile')


def offer_for_recorded(recorded: Sequence[QosProfile]) -> QosProfile:
    """QoS for a playback publisher of a topic recorded with the `recorded` offers."""
    if not recorded:
        return QosProfile()
    first = recorded[0]
    same = all((p.reliability, p.durability, p.deadline_ns, p.liveliness,
                p.liveliness_lease_duration_ns)
               == (first.reliability, first.durability, first.deadline_ns, first.liveliness,
                   first.liveliness_lease_duration_ns) for p in recorded[1:])
    if not same:
        return QosProfile()
    return replace(first, history='keep_last', depth=DEFAULT_DEPTH)
