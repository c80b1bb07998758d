"""The plant as its latched ``plant_info`` (PlantInfo) describes it, for the nodes that use it.

One description for the learner (dt, bounds and state box of its source systems, theta for
the oracle) and the controller (dt, bounds, outputs, the NMPC's family, the clock mode), built
from the message in one place (:meth:`PlantDescription.of`). No rclpy, no message import: any
object with PlantInfo's fields will do.
"""
from dataclasses import dataclass
import math
from typing import Any, Tuple


@dataclass
class PlantDescription:
    """What the nodes use of PlantInfo.

    Attributes:
        family: registered family name ('' for an unnamed plant).
        dt: sample time, s.
        u_min, u_max: input bounds, one per input.
        n_y: number of outputs.
        lockstep: the plant steps only on inputs (clock mode 'lockstep'), else real time.
        theta: parameter vector (n_theta values; empty when unknown, e.g. a real plant).
        substeps: RK4 sub-steps per sample (0: not simulated).
        state_bound: |x|_inf beyond which the plant is declared diverged.
    """

    family: str
    dt: float
    u_min: Tuple[float, ...]
    u_max: Tuple[float, ...]
    n_y: int
    lockstep: bool
    theta: Tuple[float, ...] = ()
    substeps: int = 0
    state_bound: float = math.inf

    @classmethod
    def of(cls, info: Any) -> 'PlantDescription':
        """The description a PlantInfo message gives."""
        return cls(family=info.family, dt=info.dt, u_min=tuple(info.u_min),
                   u_max=tuple(info.u_max), n_y=len(info.output_names),
                   lockstep=info.clock_mode == 'lockstep', theta=tuple(info.theta),
                   substeps=info.substeps, state_bound=info.state_bound)
