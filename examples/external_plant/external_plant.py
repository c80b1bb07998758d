#!/usr/bin/env python3
"""A plant that is not metampc's: a stand-in for a real robot, written against metampc_msgs only.

It imports rclpy and the message packages, nothing of metampc: what a driver of a real
machine would do to be controlled by the learner and the controller. The "machine" here is a
mass on a spring with a stiffening spring and viscous friction, integrated by its own
semi-implicit Euler steps at 1 kHz (not metampc's RK4), run in real time:

    p'' = (-k p - k3 p^3 - c p' + f) / m,   m = 1.0 kg, k = 1.2 N/m, k3 = 0.8 N/m^3, c = 0.3 N s/m

The learner is told a family that resembles it (`-p family:=duffing`: its source systems have
the same inputs and outputs), adapts on what this plant publishes, and the controller tracks
on it; neither knows these equations. The contract it keeps (docs/families.md, "A plant of
your own"):

* ``y`` (PlantOutput, reliable, depth 1000): step k (from 0 after a reset), y_k = (p, p')
  in m and m/s, the force held over (k-1, k] that produced it, saturated/diverged flags;
* ``plant_info`` (PlantInfo, reliable + transient_local, depth 1): dt, the force bounds, the
  names and units of the inputs and outputs, clock mode 'realtime'; no theta (unknown);
* ``u`` (ControlInput): the force to hold from the next sample on (clipped to the bounds);
* ``reset`` (ResetPlant): back to x0 (theta must be empty: this plant has none to set).

Usage: python examples/external_plant/external_plant.py [dt_s] (default 0.1), under
`source scripts/env.sh` (for the message packages) or any ROS 2 Jazzy environment that has
metampc_msgs; Ctrl-C stops it.
"""
import math
import sys

from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput
from metampc_msgs.srv import ResetPlant
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

MASS, K, K3, DAMPING = 1.0, 1.2, 0.8, 0.3
F_MAX = 1.0           # N
INNER_STEPS = 100     # integration steps per sample
BOUND = 10.0          # |p|, |p'| beyond it: diverged


class ExternalPlant(Node):
    def __init__(self, dt: float):
        super().__init__('plant')
        self.dt = dt
        self.x = [0.0, 0.0]
        self.f = 0.0            # force held over the current sample
        self.next_f = 0.0       # the latest input: held from the next sample on
        self.step = 0
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_y = self.create_publisher(PlantOutput, 'y', reliable)
        self.pub_info = self.create_publisher(PlantInfo, 'plant_info', latched)
        self.create_subscription(ControlInput, 'u', self.on_u, reliable)
        self.create_service(ResetPlant, 'reset', self.on_reset)
        self.pub_info.publish(PlantInfo(
            family='external_spring', dt=dt, u_min=[-F_MAX], u_max=[F_MAX],
            input_names=['f'], input_units=['N'], output_names=['p', 'v'],
            output_units=['m', 'm/s'], clock_mode='realtime', rate_hz=1.0 / dt,
            state_bound=BOUND))
        self.publish()
        self.create_timer(dt, self.tick)

    def on_u(self, msg: ControlInput) -> None:
        if len(msg.u) == 1 and math.isfinite(msg.u[0]):
            self.next_f = min(max(msg.u[0], -F_MAX), F_MAX)

    def on_reset(self, request, response):
        if len(request.theta):
            response.success, response.message = False, 'this plant has no theta to set'
            return response
        self.x = list(request.x0) if len(request.x0) == 2 else [0.0, 0.0]
        self.f = self.next_f = 0.0
        self.step = 0
        self.publish()
        response.success, response.message = True, f'reset to {self.x}'
        return response

    def tick(self) -> None:
        self.f = self.next_f
        h = self.dt / INNER_STEPS
        p, v = self.x
        for _ in range(INNER_STEPS):    # semi-implicit Euler
            v += h * (-K * p - K3 * p ** 3 - DAMPING * v + self.f) / MASS
            p += h * v
        self.x = [p, v]
        self.step += 1
        self.publish()

    def publish(self) -> None:
        msg = PlantOutput(step=self.step, y=list(self.x), u_applied=[self.f],
                          diverged=max(abs(v) for v in self.x) > BOUND)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_y.publish(msg)


def main() -> int:
    rclpy.init()
    node = ExternalPlant(float(sys.argv[1]) if len(sys.argv) > 1 else 0.1)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
