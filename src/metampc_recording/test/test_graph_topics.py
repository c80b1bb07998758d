"""Which topics the recorder and the live view take when given no list (graph_topics)."""
import pytest

from metampc_recording.graph_topics import default_topic


@pytest.mark.parametrize('topic, namespace, clock, taken', [
    ('/y', '/', False, True),
    ('/rosout', '/', False, False),
    ('/parameter_events', '/', False, False),
    ('/clock', '/', False, False),
    ('/clock', '/', True, True),
    ('/_hidden', '/', False, False),
    ('/a/_b/c', '/', False, False),
    ('/ns1/y', '/ns1', False, True),
    ('/ns1/deep/y', '/ns1/', False, True),
    ('/y', '/ns1', False, False),
    ('/ns10/y', '/ns1', False, False),      # a namespace is a whole token
])
def test_default_topic(topic, namespace, clock, taken):
    assert default_topic(topic, namespace, clock) is taken
