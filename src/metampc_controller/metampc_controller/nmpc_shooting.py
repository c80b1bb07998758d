"""The true-model NMPC's problem on CasADi: multiple shooting, exact derivatives, IPOPT.

The family's ``rhs`` and ``output`` (operators and numpy functions that CasADi's SX symbols
take too) and the RK4 of :mod:`metampc_plant.integrate` run on symbols unchanged: one statement
of the equations for the simulator and the planner (test_nmpc_shooting). A family whose
equations take no symbols or give other numbers on them raises :class:`SymbolicError`, and the
NMPC keeps L-BFGS-B. The NLP over w = [u_1..u_N; x_1..x_{N+T}], parameters [x_0; u_0; r; theta]:

    min  sum_{k=1}^{N+T} ||g(x_k, u_k) - r_k||_Q^2 + sum_{k=1}^{N} ||u_k - u_{k-1}||_R^2
    s.t. x_k = F(x_{k-1}, u_k; theta) (u_k = u_N for k > N),  u_min <= u_k <= u_max

F one RK4 sample, g the output, T the tail (scored against r_N): :meth:`Nmpc.costs`'s cost.
"""
from dataclasses import dataclass
import math
from typing import Optional

import casadi as ca
import numpy as np

from metampc_plant.family import PlantFamily
from metampc_plant.integrate import rk4_components, rk4_sample

# numpy functions on CasADi symbols return CasADi symbols (the 3.7 behaviour, without its
# notice): what lets the families' numpy equations build the symbolic ones.
ca.GlobalOptions.setNumpyMode(-1)

# IPOPT's success; any other return status is a solve that did not converge.
SOLVED = 'Solve_Succeeded'


class SymbolicError(ValueError):
    """The family's equations cannot be evaluated on CasADi symbols."""


def symbolic_sample(family: PlantFamily, dt: float, substeps: int) -> ca.Function:
    """F(x (n_x), u (n_u), theta (n_theta)) -> (x after dt (n_x), y there (n_y)): one sample
    of the family's RK4 with u held, and its output g(x, u, theta), as a CasADi Function.

    Raises:
        SymbolicError: the equations do not take CasADi symbols, or give other numbers on
            them than the simulator at the family's x0, x0_low and x0_high (one line).
    """
    x = ca.SX.sym('x', family.n_x)
    u = ca.SX.sym('u', family.n_u)
    theta = ca.SX.sym('theta', family.n_theta)
    comps = [ca.vertsplit(v) for v in (x, u, theta)]
    try:
        x_next = ca.vertcat(*rk4_components(family, *comps, dt, substeps))
        y_next = ca.vertcat(*family.output(ca.vertsplit(x_next), comps[1], comps[2]))
    except Exception as err:     # whatever the family's code raises on a symbol
        raise SymbolicError(f'family {family.name}: its equations do not take CasADi '
                            f'symbols ({type(err).__name__}: {err})') from None
    sample = ca.Function('sample', [x, u, theta], [x_next, y_next])
    # Some numeric code takes a symbol silently and wrongly (math.sin gives NaN): the
    # sample is checked against the simulator's at the family's x0 box corners.
    xs = np.array([family.x0, family.x0_low, family.x0_high], dtype=float)
    us = np.tile(0.5 * (np.asarray(family.u_min) + np.asarray(family.u_max)), (3, 1))
    us = np.where(np.isfinite(us), us, 0.0)
    ths = np.tile(family.nominal_theta, (3, 1))
    want = rk4_sample(family, xs, us, ths, dt, substeps)
    got = np.asarray(sample.map(3)(xs.T, us.T, ths.T)[0]).T
    if not np.allclose(got, want, rtol=1e-9, atol=1e-12):
        raise SymbolicError(f'family {family.name}: its equations on CasADi symbols differ '
                            f'from the simulator\'s (numeric code that takes no symbol)')
    return sample


@dataclass
class ShootingResult:
    """One IPOPT solve.

    Attributes:
        u: (N, n_u) planned inputs; x: (N + T, n_x) planned states.
        status: 'solved', or 'stopped: <IPOPT's return status>'.
        success: IPOPT converged (its tolerance met).
        iterations: IPOPT iterations.
        residual: max of IPOPT's primal and dual infeasibility at its last iterate (its
            scaled NLP; NaN where it reports none).
        lam_g, lam_x: the multipliers (the next solve's warm start).
    """

    u: np.ndarray
    x: np.ndarray
    status: str
    success: bool
    iterations: int
    residual: float
    lam_g: Optional[np.ndarray] = None
    lam_x: Optional[np.ndarray] = None


class MultipleShooting:
    """The NLP of the module docstring for one (family, horizon, tail, weights, bounds),
    built once (CasADi SX, exact Hessian; a few tenths of a second), solved per tick with
    other x_0, u_0, references and theta."""

    def __init__(self, family: PlantFamily, horizon: int, tail: int, q: np.ndarray,
                 r: np.ndarray, u_min: np.ndarray, u_max: np.ndarray, dt: float,
                 substeps: int, max_iter: int, tol: float):
        sample = symbolic_sample(family, dt, substeps)
        n_x, n_u, n_y, n_th = family.n_x, family.n_u, family.n_y, family.n_theta
        n, n_k = horizon, horizon + tail
        self.shape = (n, n_k, n_x, n_u)
        u = ca.SX.sym('u', n_u, n)
        x = ca.SX.sym('x', n_x, n_k)
        x0, u0 = ca.SX.sym('x0', n_x), ca.SX.sym('u0', n_u)
        ref = ca.SX.sym('r', n_y, n)
        theta = ca.SX.sym('theta', n_th)
        q_w, cost, gaps = ca.DM(q), 0, []
        x_prev = x0
        for k in range(n_k):
            x_next, y_next = sample(x_prev, u[:, min(k, n - 1)], theta)
            gaps.append(x_next - x[:, k])
            err = y_next - ref[:, min(k, n - 1)]
            cost += ca.dot(q_w * err, err)
            x_prev = x[:, k]
        du = u - ca.horzcat(u0, u[:, :-1])
        j_du = ca.dot(ca.repmat(ca.DM(r), 1, n) * du, du)             # sum_k du_k' R du_k
        p = ca.vertcat(x0, u0, ca.vec(ref), theta)
        nlp = {'x': ca.vertcat(ca.vec(u), ca.vec(x)), 'p': p, 'f': cost + j_du,
               'g': ca.vertcat(*gaps)}
        # The same cost with the states eliminated (single shooting: the plan's own J and
        # outputs y_1..y_N, as Nmpc.costs and Nmpc.rollout compute them in numpy).
        cost, ys, x_k = j_du, [], x0
        for k in range(n_k):
            x_k, y_k = sample(x_k, u[:, min(k, n - 1)], theta)
            err = y_k - ref[:, min(k, n - 1)]
            cost += ca.dot(q_w * err, err)
            ys.append(y_k)
        self._evaluate = ca.Function('evaluate', [ca.vec(u), p],
                                     [cost, ca.vec(ca.horzcat(*ys[:n]))])
        self._solver = ca.nlpsol('nmpc', 'ipopt', nlp, {
            'print_time': False, 'error_on_fail': False,
            'ipopt': {'print_level': 0, 'sb': 'yes', 'max_iter': max_iter, 'tol': tol,
                      'mu_strategy': 'adaptive', 'bound_relax_factor': 0.0}})
        inf = np.full(n_k * n_x, np.inf)
        self._lbx = np.r_[np.tile(u_min, n), -inf]
        self._ubx = np.r_[np.tile(u_max, n), inf]
        self._n_g = n_k * n_x

    def evaluate(self, plan: np.ndarray, x0: np.ndarray, u_prev: np.ndarray,
                 y_ref: np.ndarray, theta: np.ndarray) -> tuple:
        """(J of plan (N n_u,) from x0 (+inf where not finite), outputs y_1..y_N (N, n_y)
        under it): :meth:`Nmpc.costs` and :meth:`Nmpc.rollout`, evaluated symbolically."""
        j, ys = self._evaluate(plan, np.r_[x0, u_prev, y_ref.reshape(-1), theta])
        j = float(j)
        return (j if math.isfinite(j) else math.inf), np.asarray(ys).reshape(y_ref.shape)

    def solve(self, x0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray, theta: np.ndarray,
              u_guess: np.ndarray, x_guess: np.ndarray, lam_g: Optional[np.ndarray] = None,
              lam_x: Optional[np.ndarray] = None) -> ShootingResult:
        """Solve from x0 (n_x,), u_prev (n_u,), y_ref (N, n_y), theta, started at u_guess
        (N, n_u), x_guess (N + T, n_x) and, where given, the multipliers of a previous solve.
        Data that are not finite are not sent to IPOPT (status 'stopped: invalid data'); then,
        and where CasADi raises, the plan u is NaN."""
        n, n_k, n_x, n_u = self.shape
        w0 = np.r_[u_guess.reshape(-1), x_guess.reshape(-1)]
        p = np.r_[x0, u_prev, y_ref.reshape(-1), theta]
        failed = np.full_like(u_guess, math.nan)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(w0))):
            return ShootingResult(failed, x_guess, 'stopped: invalid data', False, 0, math.nan)
        args = dict(x0=w0, p=p, lbx=self._lbx, ubx=self._ubx, lbg=0.0, ubg=0.0)
        if lam_g is not None:
            args.update(lam_g0=lam_g, lam_x0=lam_x)
        try:
            sol = self._solver(**args)
        except RuntimeError as err:          # an evaluation error CasADi raises
            return ShootingResult(failed, x_guess, f'stopped: {err}'.splitlines()[0], False,
                                  0, math.nan)
        stats = self._solver.stats()
        w = np.asarray(sol['x']).reshape(-1)
        its = stats.get('iterations') or {}
        pr, du = its.get('inf_pr') or [math.nan], its.get('inf_du') or [math.nan]
        status = stats.get('return_status', 'unknown')
        success = status == SOLVED
        return ShootingResult(
            u=w[:n * n_u].reshape(n, n_u), x=w[n * n_u:].reshape(n_k, n_x),
            status='solved' if success else f'stopped: {status}', success=success,
            iterations=int(stats.get('iter_count', 0)), residual=float(max(pr[-1], du[-1])),
            lam_g=np.asarray(sol['lam_g']).reshape(-1), lam_x=np.asarray(sol['lam_x']).reshape(-1))


__all__ = ['SOLVED', 'SymbolicError', 'symbolic_sample', 'ShootingResult', 'MultipleShooting']
