"""rosbag2's QoS rules (metampc_recording.rosbag2_qos) against an independent statement of them."""
from itertools import product

from metampc_recording.rosbag2_qos import QosProfile, request_for_offers
import pytest


def offer(reliability: str, durability: str) -> QosProfile:
    """A publisher's profile as the graph reports it (history unknown, depth 0)."""
    return QosProfile(history='unknown', depth=0, reliability=reliability,
                      durability=durability, liveliness='automatic')


# Every reliability x durability a publisher may offer.
OFFERS = [offer(r, d) for r, d in product(('reliable', 'best_effort'),
                                          ('volatile', 'transient_local'))]


def rosbag2_request(offers, depth: int) -> QosProfile:
    """rosbag2_transport's Rosbag2QoS::adapt_request_to_offers (Jazzy), written as it counts:
    reliable iff every publisher is reliable, transient_local iff every one is; no publisher:
    the default profile (reliable, volatile)."""
    n = len(offers)
    reliable = sum(p.reliability == 'reliable' for p in offers)
    latched = sum(p.durability == 'transient_local' for p in offers)
    return QosProfile(history='keep_last', depth=depth,
                      reliability='reliable' if reliable == n else 'best_effort',
                      durability='transient_local' if n and latched == n else 'volatile')


@pytest.mark.parametrize('publishers', [0, 1, 2, 3])
def test_request_for_offers_follows_rosbag2_for_every_mix_of_publishers(publishers):
    for offers in product(OFFERS, repeat=publishers):
        assert request_for_offers(offers, 7) == rosbag2_request(offers, 7), offers


def test_one_weaker_publisher_makes_the_request_weaker():
    """A reliable request does not match a best-effort publisher, and a transient_local request
    does not match a volatile one: one such publisher among others decides the policy."""
    cases = [
        ([offer('reliable', 'transient_local'), offer('best_effort', 'transient_local')],
         ('best_effort', 'transient_local')),
        ([offer('reliable', 'transient_local'), offer('reliable', 'volatile')],
         ('reliable', 'volatile')),
        ([offer('best_effort', 'transient_local'), offer('reliable', 'volatile')],
         ('best_effort', 'volatile')),
        ([offer('reliable', 'transient_local')] * 3 + [offer('best_effort', 'volatile')],
         ('best_effort', 'volatile')),
        ([offer('reliable', 'transient_local')] * 3, ('reliable', 'transient_local')),
        ([], ('reliable', 'volatile')),
    ]
    for offers, expected in cases:
        request = request_for_offers(offers, 1000)
        assert (request.reliability, request.durability) == expected, offers
        assert (request.history, request.depth) == ('keep_last', 1000)
