"""Whether and how long the writers of y, u and mpc_status wait for a reader that keeps all
(the parameters of :mod:`.held_publisher`, whose ``held_qos`` makes the writers' QoS of them),
declared once for the plant and the controller. No rclpy here: the params modules that use it
stay free of it."""
from dataclasses import dataclass

from metampc_common.params import param


@dataclass
class HoldConfig:
    """Whether and how long the writers of y (plant), u and mpc_status (controller) wait for a
    reader that keeps all.

    Attributes:
        hold_for_readers: writers keep all (:data:`HELD`); false: keep the last 1000
            (qos.BACKLOG), as before: a reader that falls further behind loses messages.
        hold_timeout: s a message may wait for room before it is dropped (and counted).
    """

    hold_for_readers: bool = param(True, 'y, u and mpc_status wait while a reader that keeps '
                                         'all (the recorder) is full (false: keep the last '
                                         '1000; a slow recorder loses messages)')
    hold_timeout: float = param(10.0, 'longest wait, s, for a full reader that keeps all; '
                                      'then the message is dropped and counted', gt=0)
