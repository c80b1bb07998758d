#!/usr/bin/env python3
"""A stand-in robot for the machine bridge, written against standard ROS messages only.

One joint on a spring with viscous friction, driven by a torque (I = 1 kg m^2):

    q'' = -K q - C q' + tau,   K = 1 N m/rad, C = 0.5 N m s/rad,   |tau| <= 2 N m

integrated by its own semi-implicit Euler steps (1 ms), in real time. It knows nothing of
metampc: like a ros2_control robot it publishes ``joint_states`` (sensor_msgs/JointState:
q, q', the torque applied; stamped by its own clock) at its own rate and takes
``effort_controller/commands`` (std_msgs/Float64MultiArray: [tau]), holding the last one.
SIGUSR1 silences it (it stops publishing joint_states, still takes commands), a second
SIGUSR1 lets it speak again: a stalled driver. The bridge's mapping for it is mapping.yaml
beside this file (docs/bridge.md).

Usage: python examples/joint_robot/joint_robot.py [rate_hz] (default 50), under
`source scripts/env.sh` or any ROS 2 Jazzy environment; Ctrl-C stops it.
"""
import math
import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

K, C, TAU_MAX = 1.0, 0.5, 2.0
STEP_S = 0.001          # integration step, s


class JointRobot(Node):
    def __init__(self, rate_hz: float):
        super().__init__('joint_robot')
        self.period = 1.0 / rate_hz
        self.q = self.qd = self.tau = 0.0
        self.silent = False
        self.pub = self.create_publisher(JointState, 'joint_states', 10)
        self.create_subscription(Float64MultiArray, 'effort_controller/commands',
                                 self.on_command, 10)
        self.create_timer(self.period, self.tick)
        signal.signal(signal.SIGUSR1, self.toggle)

    def toggle(self, signum, frame) -> None:
        self.silent = not self.silent

    def on_command(self, msg: Float64MultiArray) -> None:
        if len(msg.data) == 1 and math.isfinite(msg.data[0]):
            self.tau = min(max(msg.data[0], -TAU_MAX), TAU_MAX)

    def tick(self) -> None:
        for _ in range(round(self.period / STEP_S)):
            self.qd += STEP_S * (-K * self.q - C * self.qd + self.tau)
            self.q += STEP_S * self.qd
        if not self.silent:
            msg = JointState(name=['joint1'], position=[self.q], velocity=[self.qd],
                             effort=[self.tau])
            msg.header.stamp = self.get_clock().now().to_msg()
            self.pub.publish(msg)


def main() -> int:
    rclpy.init()
    node = JointRobot(float(sys.argv[1]) if len(sys.argv) > 1 else 50.0)
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
