"""SpunNode.call: a request whose answer never comes is resent when that is asked for.

A request sent while no server exists reaches nobody, as a response dropped by the middleware
would: the first send of each call below is lost by construction, whatever the timing.
"""
import sys
import threading

from metampc_msgs.srv import SetBuffering
import pytest

from metampc_testing import TestNode


@pytest.fixture
def pair():
    caller, server = TestNode('spun_caller'), TestNode('spun_server')
    yield caller, server
    caller.close()
    server.close()


def serve_after(server, delay: float, calls: list) -> threading.Timer:
    """Create the service `delay` s from now; its callback records each request."""
    def create():
        def on_request(request, response):
            calls.append(request.buffering)
            response.success, response.kept = True, len(calls)
            return response
        server.node.create_service(SetBuffering, 'spun_service', on_request)
    timer = threading.Timer(delay, create)
    timer.start()
    return timer


def test_an_unanswered_request_is_resent_and_answered(pair):
    caller, server = pair
    client = caller.node.create_client(SetBuffering, 'spun_service')
    calls = []
    serve_after(server, 1.0, calls)
    response = caller.call(client, SetBuffering.Request(buffering=False), 30.0,
                           resend_every=0.5)
    assert response.success and calls and response.kept == len(calls)


def test_without_resend_the_lost_request_times_out(pair):
    caller, server = pair
    client = caller.node.create_client(SetBuffering, 'spun_service')
    calls = []
    serve_after(server, 0.5, calls)
    # The service comes up while the call waits, after its only send: no answer ever comes.
    with pytest.raises(AssertionError, match='timed out after 3.0 s'):
        caller.call(client, SetBuffering.Request(buffering=False), 3.0)
    assert calls == []


def test_close_under_a_busy_spin_leaves_the_spin_thread_unharmed(monkeypatch):
    """close() while the executor's thread spins on a 1-kHz timer: the thread ends without an
    exception (rclpy's Executor.shutdown destroyed the guard condition under a spin)."""
    errors = []
    monkeypatch.setattr(threading, 'excepthook', lambda args: errors.append(args.exc_value))
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)    # the threads swap often: close() lands inside a spin
    try:
        for _ in range(50):
            node = TestNode('spun_busy')
            node.node.create_timer(0.001, lambda: None)
            node.close()
    finally:
        sys.setswitchinterval(interval)
    assert errors == []
