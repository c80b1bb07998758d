"""One lockstep episode of the controller core against the plant core, in one process (no ROS).

What a lockstep run of the nodes computes, sample for sample: the plant resets to (theta, x0)
and sends y_0 with u_0 = 0; for k = 0..steps-1 the controller observes (k, u_k, y_k) with
theta(k dt) (as y_k carries it) and its tick answers u_{k+1}, held over (k, k+1] by the plant
(clipped to its bounds) to give y_{k+1}. The tracking cost pairs y_{k+1} with the reference
r_{k+1} of the tick that answered step k (``metrics.reference_pairs``) over the tracked outputs.
It stops at the first diverged sample, as a run bounded by ``stop_at_escape`` does. Used to
score controller settings in seconds (scripts/retrack.py), by the tests as the loop of the
nodes, and by Algorithm 1's online collection (warm-up inputs, eq. (ub)'s noise on answers).
"""
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence

import numpy as np

from metampc_controller.adaptation_trigger import Request
from metampc_controller.controller_core import ControllerCore, TickResult
from metampc_plant.simulator import Plant

# run_episode's learner in one process: (core, request, u_0..u_k, y_0..y_k) -> None.
Learner = Callable[[ControllerCore, Request, np.ndarray, np.ndarray], None]


@dataclass
class Episode:
    """One closed-loop episode.

    Attributes:
        u: (K + 1, n_u) inputs u_0..u_K (u_0 = 0, before any answer), as the plant held them.
        y: (K + 1, n_y) outputs y_0..y_K.
        y_ref: (K, n_y) references r_1..r_K (first row of each tick's horizon; NaN where no
            tick answered: warm-up).
        ticks: the TickResults of steps W..K-1 (W warm-up inputs).
        escaped_at: index k of the first diverged y_k, or None.
    """

    u: np.ndarray
    y: np.ndarray
    y_ref: np.ndarray
    ticks: List[TickResult]
    escaped_at: Optional[int]

    def tracking_cost(self, tracked: Sequence[int]) -> float:
        """sum_k ||y_k - r_k||^2 over the tracked outputs, k = 1..K (the experiment's cost)."""
        err = self.y[1:, list(tracked)] - self.y_ref[:, list(tracked)]
        return float(np.sum(err ** 2))


def run_episode(core: ControllerCore, plant: Plant, steps: int,
                theta: Optional[Sequence[float]] = None,
                x0: Optional[Sequence[float]] = None,
                warmup: Optional[np.ndarray] = None,
                noise: Optional[np.ndarray] = None,
                learner: Optional[Learner] = None) -> Episode:
    """Reset `plant` to (theta, x0) and let `core` answer `steps` samples (module docstring).

    The core keeps its model and tuning across episodes; a plant reset is a new episode for it
    (the step index goes back), so its planners start cold, as in the nodes.

    Args:
        warmup: (W, n_u) inputs u_1..u_W the plant holds before the core answers: the core
            observes samples 0..W-1 without a tick and answers from step W on.
        noise: (steps - W, n_u) added to the answers of steps W, W + 1, ... in turn before
            the plant clips them (eq. (ub)'s exploration).
        learner: called with the core, each adaptation request a tick makes and the samples
            u_0..u_k, y_0..y_k up to its step k: the learner in one process, which offers its
            answer to the core (``ControllerCore.offer``) or refuses
            (``core.gate.learner_refused``) before the next sample.
    """
    y0 = plant.reset(theta, x0)
    n_u = plant.family.n_u
    n_warm = 0 if warmup is None else len(warmup)
    u = np.zeros((steps + 1, n_u))
    y = np.zeros((steps + 1, len(y0)))
    y[0] = y0
    refs, ticks, escaped = [], [], (0 if plant.diverged else None)
    no_ref = np.full(len(y0), np.nan)
    k = 0
    theta_k = plant.theta     # theta(k dt), as y_k carries it
    while k < steps and escaped is None:
        core.observe(k, u[k], y[k], theta_k)
        if k < n_warm:
            u_next = warmup[k]
            refs.append(no_ref)
        else:
            res = core.tick()
            ticks.append(res)
            refs.append(res.y_ref[0] if len(res.y_ref) else no_ref)
            u_next = res.u if noise is None else res.u + noise[k - n_warm]
            if learner is not None and res.request is not None:
                learner(core, res.request, u[:k + 1], y[:k + 1])
        u[k + 1], _ = plant.saturate(u_next)
        y[k + 1] = plant.step(u[k + 1])
        theta_k = plant.theta
        k += 1
        if plant.diverged:
            escaped = k
    return Episode(u=u[:k + 1], y=y[:k + 1], y_ref=np.array(refs).reshape(k, len(y0)),
                   ticks=ticks, escaped_at=escaped)
