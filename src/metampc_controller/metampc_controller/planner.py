"""The planner contract: the settings every planner shares, its call, its one result type.

Both planners of the controller, the latent MPC of eq. (mpc) (:mod:`mpc`, on the learned NSSM
of eq. (SSM)) and the true-model NMPC (:mod:`nmpc`, the yardstick), minimise the tracking
cost of eq. (mpc) over the horizon N under input bounds; :class:`PlannerConfig` declares
those settings once. Each is a :class:`Planner`, built by name outside the tick
(:mod:`planner_registry`), and answers with a :class:`PlanResult`, so that the controller's
tick, MpcStatus and the reports read one type whichever planner answered.
"""
from dataclasses import dataclass, field, fields
import math
from typing import Optional, Protocol, Sequence, Tuple, Union

import numpy as np

from metampc_common.params import check_fields, param

Weights = Union[float, Sequence[float]]


@dataclass
class PlannerConfig:
    """The tracking problem of eq. (mpc), shared by every planner (physical units).

    Attributes:
        horizon: N, samples.
        q: output weights Q = diag(q), (n_y,), >= 0; the default tracks x1 only.
        r: Delta-u weights R = diag(r), (n_u,) or one value for all inputs, > 0.
        u_min, u_max: input bounds, (n_u,) or one value; +-inf for none.
    """

    horizon: int = param(20, 'MPC horizon N, samples', ge=1, live=True)
    q: Sequence[float] = param((1.0, 0.0), 'output tracking weights Q = diag(q), one per plant '
                                           'output (the default tracks x1 only)', ge=0,
                               live=True)
    r: Weights = param((0.05,), 'Delta-u weights, one per input (one value: every input)',
                       gt=0, scalar=True, live=True)
    u_min: Weights = param((-1.0,), 'input lower bounds, one per input (one value: every '
                                    'input; <= u_max)', scalar=True, live=True)
    u_max: Weights = param((1.0,), 'input upper bounds, one per input (one value: every '
                                   'input; >= u_min)', scalar=True, live=True)

    def __post_init__(self):
        q = np.asarray(self.q, dtype=float)
        r = np.asarray(self.r, dtype=float)
        lo, hi = np.asarray(self.u_min, dtype=float), np.asarray(self.u_max, dtype=float)
        check_fields(self, skip=('q', 'r', 'u_min', 'u_max'))   # vectors, checked here
        if q.ndim != 1 or not np.all(np.isfinite(q)) or np.any(q < 0):
            raise ValueError(f'q must be a vector of finite weights >= 0, got {self.q}')
        if not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise ValueError(f'r must be finite and > 0, got {self.r}')
        sizes = {v.size for v in (r, lo, hi)} - {1}
        if len(sizes) > 1 or any(v.ndim > 1 for v in (r, lo, hi)):
            raise ValueError(f'r, u_min and u_max need one value per input (or one for all), '
                             f'got {self.r}, {self.u_min}, {self.u_max}')
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
            raise ValueError(f'need u_min <= u_max, got {self.u_min}, {self.u_max}')

    @property
    def n_u(self) -> int:
        """Inputs the weights and bounds are for: their longest length (1: any)."""
        return max(np.size(self.r), np.size(self.u_min), np.size(self.u_max))

    def bounds(self, n_u: int) -> Tuple[np.ndarray, np.ndarray]:
        """(u_min, u_max), each broadcast to shape (n_u,)."""
        return tuple(np.broadcast_to(np.asarray(v, dtype=float), (n_u,)).copy()
                     for v in (self.u_min, self.u_max))

    def shared(self) -> dict:
        """This config's :class:`PlannerConfig` fields, {name: value}: what another
        planner's config takes of it (``NmpcConfig(**mpc.shared(), dt=...)``)."""
        return {f.name: getattr(self, f.name) for f in fields(PlannerConfig)}


@dataclass
class PlanResult:
    """One plan at tick t (latent MPC or NMPC).

    Attributes:
        u: (n_u,) input to apply over (t, t+1], u_{t+1} (read-only, a view of u_plan).
        u_plan: (N, n_u) planned inputs u_{t+1..t+N}; always finite and within the bounds
            (read-only: the next tick warm-starts from it).
        y_pred: (N, n_y) outputs y_{t+1..t+N} predicted under u_plan (nan if the data were not
            finite).
        cost: the plan's cost J. Latent MPC: at OSQP's solution (obj_val + b'b: before the
            clip into the bounds, which moves it by O(eps_abs)), J(u_plan) on a fallback, nan
            if the data were not finite; NMPC: J of the plan on the true model.
        status: the solver's status: OSQP's, or 'invalid data' when z_t, u_t or the reference
            were not finite (then OSQP does not run; pass finite values for untracked outputs
            too); the NMPC's 'solved' or 'stopped: <IPOPT's status or L-BFGS-B's message>'.
        iterations: solver iterations (0 when OSQP did not run).
        solve_time: wall-clock time of the whole solve() call, s.
        fallback: True when u_plan is the shifted previous plan (or held u_t), not a solution
            (NMPC: its non-finite cost left the warm start).
        terminal_fallback: True when the terminal weight is the output-weight fallback (latent
            MPC only).
        disturbance: (n_d,) latent MPC's offset-free disturbance estimate p the plan used
            (empty with 'none', and for the NMPC).
        slack: latent MPC: the largest planned violation of the soft output bounds (0 without
            them, or when the plan meets them).
        residual: the solver's optimality residual where it reports one (the NMPC's IPOPT:
            max of its primal and dual infeasibility at the last iterate), else NaN.
    """

    u: np.ndarray
    u_plan: np.ndarray
    y_pred: np.ndarray
    cost: float
    status: str
    iterations: int
    solve_time: float
    fallback: bool = False
    terminal_fallback: bool = False
    disturbance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slack: float = 0.0
    residual: float = math.nan


class Planner(Protocol):
    """A receding-horizon planner, called once per tick.

    Built for one (config, model) by its registry factory, outside the tick (the latent MPC's
    OSQP set-up and DARE take milliseconds): a new model or a new config is a new planner,
    swapped in between two ticks as one reference. A new plant episode is :meth:`reset`.
    """

    def solve(self, state: Optional[np.ndarray], u_prev: np.ndarray, y_ref: np.ndarray,
              y: Optional[np.ndarray] = None, step: Optional[int] = None) -> PlanResult:
        """Plan u_{t+1..t+N} at the tick answering sample t.

        Args:
            state: the state the plan starts from where the caller has it: the latent MPC's
                z_t (eq. (z): the tick encodes it, the model's prediction error reads it too);
                the NMPC's plant state x_t, or None to estimate it from y.
            u_prev: (n_u,) the applied input u_t.
            y_ref: (N, n_y) references r_{t+1..t+N}.
            y: (n_y,) the measured y_t.
            step: t, the sample's index (a skipped sample is not read as one step).
        """

    def reset(self) -> None:
        """Start cold, as freshly built: a new plant episode."""

    def set_time_limit(self, seconds: float) -> None:
        """The solver's wall-clock cap per solve from the next solve on, in place (warm start
        kept): the controller lifts it under a lockstep plant, which waits for every answer."""


__all__ = ['Weights', 'PlannerConfig', 'PlanResult', 'Planner']
