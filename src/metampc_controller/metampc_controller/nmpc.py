"""Nonlinear MPC on the true plant model: the tracking yardstick (not the paper's method).

Eq. (mpc)'s cost (the latent MPC's horizon, weights and bounds, Q on the terminal output, the
tail) predicted by the family's own equations (RK4) with the true theta: the physical limit for
this cost. Solvers (``NmpcConfig.solver``): 'ipopt', multiple shooting on CasADi with exact
derivatives (:mod:`nmpc_shooting`), warm-started from the shifted plan and states; 'lbfgsb',
single shooting by L-BFGS-B with forward differences (the yardstick until 2026-12-07, and what a
family without a symbolic form keeps). Where IPOPT stops unconverged, L-BFGS-B runs from the same
start and the cheapest of the two plans and the shifted previous one flies (the shifted plan is
the ``fallback``). A :class:`~planner.Planner`; theta may change between solves
(:meth:`Nmpc.set_theta`); the state is estimated from y (``PlantFamily.state_from_output``).
"""
from dataclasses import dataclass
import math
import time
from typing import Optional, Sequence

import numpy as np
from scipy.optimize import minimize

from metampc_controller.nmpc_shooting import MultipleShooting, SymbolicError
from metampc_controller.planner import PlannerConfig, PlanResult
# The plant's equations (the controller's other import of the plant package is closed_loop's
# plant core, a harness outside the node).
from metampc_plant.family import PlantFamily
from metampc_plant.integrate import rk4_sample

SOLVERS = ('ipopt', 'lbfgsb')


@dataclass
class NmpcConfig(PlannerConfig):
    """Settings of the nonlinear MPC: the shared horizon, weights and bounds
    (:class:`~metampc_controller.planner.PlannerConfig`) and its own.

    Attributes:
        dt: sample time, s.
        substeps: RK4 steps per sample of the prediction (why 2: docs/controller.md,
            Planners).
        solver: one of SOLVERS (module docstring).
        max_iter: L-BFGS-B iteration cap per solve.
        fd_step: forward-difference step on u (L-BFGS-B).
        ipopt_max_iter: IPOPT iteration cap per solve.
        ipopt_tol: IPOPT's convergence tolerance (its scaled NLP error).
        tail: samples predicted past N with the last planned input held, each output scored
            against the last reference with Q (no Delta-u: the input is held): a terminal
            cost on the true model that stands for the cost-to-go, as the DARE's does for the
            latent MPC (0: none, eq. (mpc) over N alone).
    """

    dt: float = 0.1
    substeps: int = 2
    solver: str = 'ipopt'
    max_iter: int = 50
    fd_step: float = 1e-6
    ipopt_max_iter: int = 200
    ipopt_tol: float = 1e-10
    tail: int = 0


class Nmpc:
    """Receding-horizon nonlinear MPC on the plant family's model with parameters theta, a
    :class:`~metampc_controller.planner.Planner`."""

    def __init__(self, config: NmpcConfig, family: PlantFamily, theta: Sequence[float]):
        self.family = family
        self.theta = np.asarray(family.check_theta(theta))
        n_u = family.n_u
        self.r, self.u_min, self.u_max = (
            np.broadcast_to(np.asarray(v, dtype=float), (n_u,)).copy()
            for v in (config.r, config.u_min, config.u_max))
        self.config = config
        self.q = np.asarray(config.q, dtype=float).reshape(family.n_y)
        if config.solver not in SOLVERS:
            raise ValueError(f'NMPC solver must be one of {", ".join(SOLVERS)}, got '
                             f'{config.solver!r}')
        # The solver in use, and why where it is not the one asked for.
        self.solver, self.solver_note = config.solver, ''
        self._shooting: Optional[MultipleShooting] = None
        if config.solver == 'ipopt':
            try:
                self._shooting = MultipleShooting(
                    family, config.horizon, config.tail, self.q, self.r, self.u_min,
                    self.u_max, config.dt, config.substeps, config.ipopt_max_iter,
                    config.ipopt_tol)
            except SymbolicError as err:
                self.solver, self.solver_note = 'lbfgsb', f'{err}: L-BFGS-B instead'
        self._plan: Optional[np.ndarray] = None     # (N n_u,)
        self._states: Optional[np.ndarray] = None   # ipopt: planned x_{t+1..t+N+T}
        self._x: Optional[np.ndarray] = None        # state estimate at the last solve

    def set_theta(self, theta: Sequence[float]) -> None:
        """The plant's theta changed (a schedule): predict with it from the next solve on,
        warm start kept. ValueError if it does not fit the family."""
        self.theta = np.asarray(self.family.check_theta(theta))

    def reset(self) -> None:
        """Forget the previous plan and state estimate: the next solve starts from u_prev held
        (a new episode)."""
        self._plan = None
        self._states = None
        self._x = None

    def set_time_limit(self, seconds: float) -> None:
        """Both solvers run without a wall-clock cap (their iteration caps bound them):
        nothing to set."""

    def rollout(self, x0: np.ndarray, plans: np.ndarray) -> np.ndarray:
        """Outputs y_{t+1..t+N} for a batch of input plans (P, N, n_u); returns (P, N, n_y)."""
        cfg, fam = self.config, self.family
        n_p, n = plans.shape[:2]
        x = np.tile(np.asarray(x0, dtype=float), (n_p, 1))
        theta = np.tile(self.theta, (n_p, 1))
        ys = np.empty((n_p, n, fam.n_y))
        with np.errstate(over='ignore', invalid='ignore'):
            for k in range(n):
                x = rk4_sample(fam, x, plans[:, k], theta, cfg.dt, cfg.substeps)
                ys[:, k] = np.stack(fam.output(x.T, plans[:, k].T, theta.T), axis=1)
        return ys

    def costs(self, x0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray,
              plans: np.ndarray) -> np.ndarray:
        """J for each plan of a batch (P, N n_u), its tail included; non-finite predictions
        cost +inf."""
        n_p, n_u = plans.shape[0], self.family.n_u
        plans = plans.reshape(n_p, -1, n_u)
        tail = self.config.tail
        if tail:    # the last input held, the last reference kept (Delta-u 0 over the tail)
            plans = np.concatenate([plans, np.repeat(plans[:, -1:], tail, axis=1)], axis=1)
            y_ref = np.concatenate([y_ref, np.repeat(y_ref[-1:], tail, axis=0)])
        err = self.rollout(x0, plans) - y_ref[None]
        track = np.einsum('pkj,j,pkj->p', err, self.q, err)
        du = np.diff(np.concatenate([np.broadcast_to(u_prev, (n_p, 1, n_u)), plans], axis=1),
                     axis=1)
        # Summed over the horizon along a contiguous axis: one input sums as a 1-D plan did.
        total = track + np.sum(np.ascontiguousarray(np.swapaxes(du * du, 1, 2)), axis=2) @ self.r
        return np.where(np.isfinite(total), total, np.inf)

    def estimate(self, y: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """The state behind the measured y_t (see the module docstring), shape (n_x,)."""
        fam = self.family
        if self._x is None:
            x_pred = np.asarray(fam.x0, dtype=float)
        else:
            x_pred = self.rollout_state(self._x, u_prev)
        self._x = fam.state_from_output(np.asarray(y, dtype=float), x_pred)
        return self._x

    def rollout_state(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The state one sample after x (n_x,) with u (n_u,) held."""
        with np.errstate(over='ignore', invalid='ignore'):
            return rk4_sample(self.family, x[None], np.asarray(u, dtype=float)[None],
                              self.theta[None], self.config.dt, self.config.substeps)[0]

    def solve(self, state: Optional[np.ndarray], u_prev: Sequence[float], y_ref: np.ndarray,
              y: Optional[np.ndarray] = None, step: Optional[int] = None) -> PlanResult:
        """Plan from the plant state x_t (n_x,), or with None from the measured y_t (n_y,)
        (:meth:`estimate`), the previous input u_t (n_u,) and references y_ref (N, n_y);
        `step` is not needed (the :class:`~metampc_controller.planner.Planner` call)."""
        cfg, n_u = self.config, self.family.n_u
        n = cfg.horizon
        start = time.perf_counter()
        u_prev = np.asarray(u_prev, dtype=float).reshape(n_u)
        if state is not None:
            x0 = self._x = np.array(state, dtype=float)
        elif y is not None:
            x0 = self.estimate(y, u_prev)
        else:
            raise ValueError('Nmpc.solve needs the state or the measured y')
        lo, hi = np.tile(self.u_min, n), np.tile(self.u_max, n)
        if self._plan is None:
            held = np.where(np.isfinite(u_prev), u_prev, 0.0)
            guess = np.tile(np.clip(held, self.u_min, self.u_max), n)
        else:
            guess = np.concatenate([self._plan[n_u:], self._plan[-n_u:]])
        solve = self._solve_shooting if self._shooting is not None else self._solve_lbfgsb
        plan, status, iterations, residual = solve(x0, u_prev, y_ref, guess, lo, hi)
        if self._shooting is not None and status != 'solved':
            # IPOPT stopped unconverged: today's L-BFGS-B from the same start too, and the
            # cheapest of its plan, IPOPT's and the shifted one flies.
            rescue = self._solve_lbfgsb(x0, u_prev, y_ref, guess, lo, hi)[0]
            plans = [p for p in (plan, rescue) if p is not guess] + [guess]
            costs = [self._evaluate(x0, u_prev, y_ref, p)[0] for p in plans]
            plan = plans[int(np.argmin(costs))] if np.isfinite(min(costs)) else guess
            if plan is rescue and rescue is not guess:
                status, self._states = f'{status} (L-BFGS-B plan)', None
        fallback = plan is guess
        if fallback:
            plan, self._states = np.clip(guess, lo, hi), None
        cost, y_pred = self._evaluate(x0, u_prev, y_ref, plan)
        plan.flags.writeable = False    # the next warm start; u_plan is a view of it
        self._plan = plan
        return PlanResult(u=plan[:n_u].copy(), u_plan=plan.reshape(n, n_u), y_pred=y_pred,
                          cost=cost, status=status, iterations=iterations,
                          solve_time=time.perf_counter() - start, fallback=fallback,
                          residual=residual)

    def _evaluate(self, x0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray,
                  plan: np.ndarray) -> tuple:
        """(J (+inf where not finite), y_pred (N, n_y)) of plan (N n_u,): on CasADi's
        compiled equations with the ipopt solver (the same numbers, in microseconds), else
        :meth:`costs` and :meth:`rollout`."""
        if self._shooting is not None:
            return self._shooting.evaluate(plan, x0, u_prev, y_ref, self.theta)
        plans = plan.reshape(1, -1, self.family.n_u)
        return (float(self.costs(x0, u_prev, y_ref, plan[None])[0]),
                self.rollout(x0, plans)[0])

    def _solve_lbfgsb(self, x0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray,
                      guess: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple:
        """L-BFGS-B single shooting: (plan (N n_u,) within [lo, hi], or `guess` itself where
        the cost is not finite; status; iterations; residual: NaN, none reported)."""
        cfg = self.config
        eye = cfg.fd_step * np.eye(guess.size)

        def fun(u):
            # Row 0 is the plan itself, the others perturb one input each (forward differences).
            j = self.costs(x0, u_prev, y_ref, np.vstack([u, u + eye]))
            with np.errstate(invalid='ignore'):     # inf - inf: data that are not finite
                return j[0], (j[1:] - j[0]) / cfg.fd_step

        res = minimize(fun, guess, jac=True, method='L-BFGS-B', bounds=list(zip(lo, hi)),
                       options={'maxiter': cfg.max_iter})
        plan = np.clip(res.x, lo, hi) if np.isfinite(res.fun) else guess
        return (plan, 'solved' if res.success else f'stopped: {res.message}', int(res.nit),
                math.nan)

    def _solve_shooting(self, x0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray,
                        guess: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple:
        """IPOPT multiple shooting from the shifted plan and states (without planned states,
        the first solve of an episode or after a fallback: every state at x0, which measured
        better than the plan's own rollout: from rest the tank's rollout drains an upper tank
        through sqrt's infinite slope at 0, where IPOPT stalled at its cap, while from x0 held
        it converged in 7 iterations to L-BFGS-B's cost): (plan (N n_u,) within [lo, hi], or
        `guess` itself where the solution is not finite; status; iterations; residual)."""
        u_guess = guess.reshape(-1, self.family.n_u)
        if self._states is None:
            states = np.tile(x0, (self.config.horizon + self.config.tail, 1))
        else:
            states = np.vstack([self._states[1:],
                                self.rollout_state(self._states[-1], u_guess[-1])])
            states = np.where(np.isfinite(states), states, x0)
        res = self._shooting.solve(x0, u_prev, y_ref, self.theta, u_guess, states)
        plan = res.u.reshape(-1)
        if not np.all(np.isfinite(plan)):
            self._states = None
            return guess, res.status, res.iterations, res.residual
        self._states = res.x
        return np.clip(plan, lo, hi), res.status, res.iterations, res.residual
