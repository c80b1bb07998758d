"""Nonlinear MPC on the true van der Pol model: the tracking yardstick (not the paper's method).

Same horizon, cost and bounds as the latent MPC of eq. (mpc), but the prediction is the plant's
own RK4 model (metampc_plant.vanderpol) with the true theta, so its tracking cost is the
physical limit for this cost. Single shooting over the N inputs u_{t+1..t+N}::

    J(u) = sum_{k=1..N} (y_{t+k} - r_{t+k})' Q (y_{t+k} - r_{t+k})
           + sum_{k=0..N-1} (u_{t+k+1} - u_{t+k})' R (u_{t+k+1} - u_{t+k}),
    u_min <= u <= u_max,

with u_t the previous applied input. Solved by L-BFGS-B (scipy) with a forward-difference
gradient whose N + 1 rollouts run as one batch of the vectorised plant model, warm-started from
the shifted previous plan. The terminal output term uses Q: the DARE weight of the latent MPC
belongs to a linear model this controller does not have.
"""
from dataclasses import dataclass
import time
from typing import Optional, Sequence

import numpy as np
from scipy.optimize import minimize

# The plant's equations: the one module of the controller that imports the plant package. Its
# input and output counts are also those the controller checks samples and parameters against.
from metampc_plant.vanderpol import N_U, N_Y, rk4_sample


@dataclass
class NmpcConfig:
    """Settings of the nonlinear MPC.

    Attributes:
        horizon: N, samples.
        q: output weights (n_y,), >= 0 (default: track x1 only).
        r: Delta-u weight, > 0.
        u_min, u_max: input bounds.
        dt: sample time, s.
        substeps: RK4 steps per sample of the prediction. 2 (h = 0.05 s) predicts the plant's
            10-substep trajectory to ~1e-5 over a 2 s horizon at a fifth of the cost.
        max_iter: L-BFGS-B iteration cap per solve.
        fd_step: forward-difference step on u.
    """

    horizon: int = 20
    q: Sequence[float] = (1.0, 0.0)
    r: float = 0.05
    u_min: float = -1.0
    u_max: float = 1.0
    dt: float = 0.1
    substeps: int = 2
    max_iter: int = 50
    fd_step: float = 1e-6


@dataclass
class NmpcResult:
    """One solve: u (first input, shape (1,)), u_plan (N, 1), y_pred (N, n_y), cost, status,
    iterations, solve_time (s)."""

    u: np.ndarray
    u_plan: np.ndarray
    y_pred: np.ndarray
    cost: float
    status: str
    iterations: int
    solve_time: float


class Nmpc:
    """Receding-horizon nonlinear MPC on the van der Pol model with damping theta."""

    def __init__(self, config: NmpcConfig, theta: float):
        if config.horizon < 1 or config.r <= 0 or config.u_min > config.u_max:
            raise ValueError('need horizon >= 1, r > 0 and u_min <= u_max')
        self.config = config
        self.theta = float(theta)
        self.q = np.asarray(config.q, dtype=float).reshape(N_Y)
        self._plan: Optional[np.ndarray] = None

    def reset(self) -> None:
        """Forget the previous plan: the next solve starts from u_prev held (a new episode)."""
        self._plan = None

    def rollout(self, x0: np.ndarray, plans: np.ndarray) -> np.ndarray:
        """Outputs y_{t+1..t+N} for a batch of input plans (P, N); returns (P, N, n_y)."""
        cfg = self.config
        n_p, n = plans.shape
        x = np.tile(np.asarray(x0, dtype=float), (n_p, 1))
        theta = np.full(n_p, self.theta)
        ys = np.empty((n_p, n, N_Y))
        with np.errstate(over='ignore', invalid='ignore'):
            for k in range(n):
                x = rk4_sample(x, plans[:, k], theta, cfg.dt, cfg.substeps)
                ys[:, k] = x
        return ys

    def costs(self, x0: np.ndarray, u_prev: float, y_ref: np.ndarray,
              plans: np.ndarray) -> np.ndarray:
        """J for each plan of a batch (P, N); non-finite predictions cost +inf."""
        err = self.rollout(x0, plans) - y_ref[None]
        track = np.einsum('pkj,j,pkj->p', err, self.q, err)
        du = np.diff(np.concatenate([np.full((plans.shape[0], 1), u_prev), plans], axis=1))
        total = track + self.config.r * np.sum(du * du, axis=1)
        return np.where(np.isfinite(total), total, np.inf)

    def solve(self, x0: np.ndarray, u_prev: float, y_ref: np.ndarray) -> NmpcResult:
        """Plan from state x0 (2,) and previous input u_prev for references y_ref (N, n_y)."""
        cfg = self.config
        n = cfg.horizon
        start = time.perf_counter()
        if self._plan is None:
            guess = np.full(n, np.clip(u_prev, cfg.u_min, cfg.u_max))
        else:
            guess = np.append(self._plan[1:], self._plan[-1])
        eye = cfg.fd_step * np.eye(n)

        def fun(u):
            # Row 0 is the plan itself, rows 1..N perturb one input each (forward differences).
            j = self.costs(x0, u_prev, y_ref, np.vstack([u, u + eye]))
            return j[0], (j[1:] - j[0]) / cfg.fd_step

        res = minimize(fun, guess, jac=True, method='L-BFGS-B',
                       bounds=[(cfg.u_min, cfg.u_max)] * n,
                       options={'maxiter': cfg.max_iter})
        plan = np.clip(res.x, cfg.u_min, cfg.u_max)
        if not np.isfinite(res.fun):
            plan = np.clip(guess, cfg.u_min, cfg.u_max)
        self._plan = plan
        y_pred = self.rollout(x0, plan[None])[0]
        return NmpcResult(u=plan[:1].copy(), u_plan=plan.reshape(n, N_U), y_pred=y_pred,
                          cost=float(self.costs(x0, u_prev, y_ref, plan[None])[0]),
                          status='solved' if res.success else f'stopped: {res.message}',
                          iterations=int(res.nit), solve_time=time.perf_counter() - start)
