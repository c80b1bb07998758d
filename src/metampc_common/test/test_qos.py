"""The graph's QoS profiles are those the docs give (the QoS columns of docs/plant.md,
controller.md, learner.md; experiments.md for the events): a change to one changes what every
node and the recordings offer."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

from metampc_common import qos

RELIABLE, VOLATILE = ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE
TRANSIENT_LOCAL = DurabilityPolicy.TRANSIENT_LOCAL


def test_profiles_as_documented():
    # name: (reliability, durability, keep_last depth), as written in the docs' QoS columns.
    expected = {'STREAM': (RELIABLE, VOLATILE, 100), 'BACKLOG': (RELIABLE, VOLATILE, 1000),
                'LATCHED': (RELIABLE, TRANSIENT_LOCAL, 1),
                'SPARSE': (RELIABLE, VOLATILE, 10), 'EVENTS': (RELIABLE, TRANSIENT_LOCAL, 1000)}
    for name, (reliability, durability, depth) in expected.items():
        profile = getattr(qos, name)
        assert profile.history == HistoryPolicy.KEEP_LAST, name
        assert (profile.reliability, profile.durability, profile.depth) == (
            reliability, durability, depth), name
