"""The soak's third process on the graph: it publishes the model to control with and records
the receive time of every ``y``, ``u`` and ``mpc_status`` (the rclpy side of
:mod:`metampc_bringup.soak.realtime_soak`)."""
import time
from typing import List, Optional

from metampc_bringup.orchestration.spun_node import SpunNode
from metampc_common.qos import BACKLOG, LATCHED
from metampc_msgs.msg import ControlInput, MpcStatus, NssmWeights, PlantOutput


class Observer:
    """Receive times (monotonic ns) and the fields the measures need, per topic, in the
    tuple layouts of :mod:`metampc_bringup.soak.soak_metrics`."""

    def __init__(self, weights: Optional[NssmWeights]):
        self.spun = SpunNode('metampc_soak', threads=1)
        node = self.spun.node
        self.y: List[tuple] = []        # (t, step, u_applied)
        self.u: List[tuple] = []        # (t, step, u, model_version)
        self.status: List[tuple] = []   # (t, step, tick_time, solve_time, fallback)
        node.create_subscription(PlantOutput, 'y', self._on_y, BACKLOG)
        node.create_subscription(ControlInput, 'u', self._on_u, BACKLOG)
        node.create_subscription(MpcStatus, 'mpc_status', self._on_status, BACKLOG)
        self.requests: List[tuple] = []     # (t, step) of the controller's adapt requests
        if weights is not None:     # else a learner publishes the model
            self.weights = node.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
            self.weights.publish(weights)

    def _on_y(self, msg: PlantOutput) -> None:
        self.y.append((time.monotonic_ns(), msg.step, msg.u_applied[0]))

    def _on_u(self, msg: ControlInput) -> None:
        self.u.append((time.monotonic_ns(), msg.step, msg.u[0], msg.model_version))

    def _on_status(self, msg: MpcStatus) -> None:
        self.status.append((time.monotonic_ns(), msg.step, msg.tick_time, msg.solve_time,
                            msg.fallback))
        if msg.adapt_request:
            self.requests.append((time.monotonic_ns(), msg.step))

    def subscribed(self, topic: str, node_name: str) -> bool:
        """Whether the node `node_name` has a subscription on `topic` (e.g. '/y')."""
        return any(i.node_name == node_name
                   for i in self.spun.node.get_subscriptions_info_by_topic(topic))

    def close(self) -> None:
        self.spun.close()
