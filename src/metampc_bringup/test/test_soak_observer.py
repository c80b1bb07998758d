"""The soak's observer against a probe that publishes y, u and mpc_status with known fields:
every message is one tuple in the layout soak_metrics reads, in publishing order, with a
monotonic receive time between the first publish and the check; the adaptation requests are
listed; the model it was given reaches a subscriber that comes later (latched)."""
import time

from metampc_bringup.soak.soak_observer import Observer
from metampc_common.qos import BACKLOG, LATCHED
from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantOutput
from metampc_testing import TestNode

N = 20


def test_the_observer_records_every_message_in_the_layouts_of_soak_metrics():
    observer, probe = Observer(NssmWeights(version=7, method='manual')), TestNode('soak_probe')
    try:
        pubs = {name: probe.node.create_publisher(kind, name, BACKLOG) for name, kind in
                (('y', PlantOutput), ('u', ControlInput), ('mpc_status', MpcStatus))}
        probe.wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 30.0,
                       "the observer's subscriptions")
        assert observer.subscribed('/y', 'metampc_soak')
        assert not observer.subscribed('/y', 'someone_else')
        start = time.monotonic_ns()
        for k in range(N):
            pubs['y'].publish(PlantOutput(step=k, u_applied=[0.5 * k]))
            pubs['u'].publish(ControlInput(step=k, u=[-0.25 * k], model_version=7))
            pubs['mpc_status'].publish(MpcStatus(step=k, tick_time=1e-4 * k,
                                                 solve_time=2e-5 * k, fallback=k % 3 == 0,
                                                 adapt_request=k in (4, 11)))
        probe.wait_for(lambda: min(len(observer.y), len(observer.u), len(observer.status)) == N,
                       30.0, 'every message at the observer')
        end = time.monotonic_ns()
        assert [r[1:] for r in observer.y] == [(k, 0.5 * k) for k in range(N)]
        assert [r[1:] for r in observer.u] == [(k, -0.25 * k, 7) for k in range(N)]
        assert [r[1:] for r in observer.status] == [
            (k, 1e-4 * k, 2e-5 * k, k % 3 == 0) for k in range(N)]
        assert [r[1] for r in observer.requests] == [4, 11]
        for rows in (observer.y, observer.u, observer.status, observer.requests):
            times = [r[0] for r in rows]
            assert times == sorted(times) and start <= times[0] and times[-1] <= end
        models = []
        probe.node.create_subscription(NssmWeights, 'nssm_weights', models.append, LATCHED)
        probe.wait_for(lambda: models, 30.0, 'the latched model')
        assert (models[0].version, models[0].method) == (7, 'manual')
    finally:
        probe.close()
        observer.close()
