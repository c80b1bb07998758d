"""`ros2 run metampc_controller send_model`: publish the hand-built NSSM on the latched
``nssm_weights`` topic and stay, so that a controller started later still gets it.

The model is :func:`metampc_model.manual_model.linearised_vdp_nssm` (the van der Pol plant
linearised at the origin; method 'manual', stage 'adapted'), encoded with
:func:`metampc_model.weights_codec.fields_from_weights`. Parameters (declared once on
:class:`SendModelConfig`): ``theta``, ``dt``, ``history``, ``version``. A bad value ends the
node with one error line and exit status 2; Ctrl-C (also during start-up) exits 0.
"""
import sys
from dataclasses import dataclass
from typing import Dict

from metampc_common.node_main import declare_parameters, run_node
from metampc_common.params import build, param, ParamSpec, Section, table
from metampc_common.qos import LATCHED
from metampc_msgs.msg import NssmWeights
from rclpy.node import Node

from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.weights_codec import fields_from_weights


@dataclass
class SendModelConfig:
    """The hand-built model to publish (each field is a parameter)."""

    theta: float = param(0.0, 'van der Pol damping of the linearisation')
    dt: float = param(0.1, "sample time of the model, s (the plant's dt)", gt=0)
    history: int = param(10, "encoder history H, samples (the controller's history, or any "
                             'when that is 0)', ge=1, le=1000)
    version: int = param(1, 'model version carried by the message', ge=1)


SECTION = Section(SendModelConfig)
PARAMETERS: Dict[str, ParamSpec] = table([SECTION])


class SendModelNode(Node):
    """Publishes one latched NssmWeights message at start-up (see the module docstring)."""

    def __init__(self):
        super().__init__('send_model')
        cfg = build(SECTION, declare_parameters(self, PARAMETERS))
        config, norm, params = linearised_vdp_nssm(cfg.theta, cfg.dt, history=cfg.history)
        self._pub = self.create_publisher(NssmWeights, 'nssm_weights', LATCHED)
        self._pub.publish(NssmWeights(version=cfg.version, method='manual', stage='adapted',
                                      **fields_from_weights(config, norm, params)))
        self.get_logger().info(
            f'published the hand-built model v{cfg.version} (theta={cfg.theta}, dt={cfg.dt} s, '
            f'H={cfg.history}) on latched {self._pub.topic_name}; Ctrl-C to stop')


def main(args=None) -> int:
    """`ros2 run metampc_controller send_model [--ros-args -p theta:=0.5 ...]`; exit code."""
    return run_node(SendModelNode, 'send_model', args)


if __name__ == '__main__':
    sys.exit(main())
