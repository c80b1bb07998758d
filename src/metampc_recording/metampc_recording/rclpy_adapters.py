"""Conversions between rclpy objects and the plain data of the recording cores.

Shared by the recorder, the player and the live view: rclpy QoSProfile <-> :class:`QosProfile`.
"""
from metampc_recording.rosbag2_qos import QosProfile
from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)


def qos_from_rclpy(profile: QoSProfile) -> QosProfile:
    """rclpy profile (e.g. of TopicEndpointInfo) -> rosbag2 policy names, durations in ns."""
    return QosProfile(
        history=profile.history.name.lower(), depth=int(profile.depth),
        reliability=profile.reliability.name.lower(),
        durability=profile.durability.name.lower(),
        deadline_ns=profile.deadline.nanoseconds, lifespan_ns=profile.lifespan.nanoseconds,
        liveliness=profile.liveliness.name.lower(),
        liveliness_lease_duration_ns=profile.liveliness_lease_duration.nanoseconds,
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def _policy(enum, name: str):
    """Enum member for a rosbag2 policy name; 'unknown' (not settable) -> system default."""
    return enum.SYSTEM_DEFAULT if name == 'unknown' else enum[name.upper()]


def qos_to_rclpy(profile: QosProfile) -> QoSProfile:
    """:class:`QosProfile` -> rclpy QoSProfile for a publisher or subscription."""
    return QoSProfile(
        history=_policy(HistoryPolicy, profile.history), depth=profile.depth,
        reliability=_policy(ReliabilityPolicy, profile.reliability),
        durability=_policy(DurabilityPolicy, profile.durability),
        deadline=Duration(nanoseconds=profile.deadline_ns),
        lifespan=Duration(nanoseconds=profile.lifespan_ns),
        liveliness=_policy(LivelinessPolicy, profile.liveliness),
        liveliness_lease_duration=Duration(nanoseconds=profile.liveliness_lease_duration_ns),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions)
