"""What every planner of the controller answers with: one result type.

The latent MPC of eq. (mpc) (:mod:`mpc`, on the learned NSSM) and the true-model NMPC
(:mod:`nmpc`, the yardstick) both return a :class:`PlanResult`, so the controller's tick,
MpcStatus and the reports read one type whichever planner answered.
"""
from dataclasses import dataclass, field

import numpy as np


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
            too); the NMPC's 'solved' or 'stopped: <L-BFGS-B's message>'.
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
