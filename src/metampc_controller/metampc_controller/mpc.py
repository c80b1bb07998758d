"""Latent linear MPC of eq. (mpc): a condensed box-constrained QP solved by OSQP.

Model: eq. (SSM)'s linear part in physical units (eqs. (z_next), (haty)), z_{k+1} = A z_k +
B u_{k+1} + e, y_k = C z_k + d, u_k held over (k-1, k]. From z_t (eq. (z)), the applied u_t and
the references r_{t+1..t+N} it plans U = [u_{t+1}; ...; u_{t+N}] within the input bounds, with
eq. (mpc)'s tracking and Delta-u cost, the DARE terminal cost (:mod:`terminal_cost`), offset-free
tracking (:mod:`offset_free`) and optional soft output bounds. Contract: :meth:`LatentMpc.
set_model` builds the QP and its OSQP factorisation once per (model, config); per tick
:meth:`LatentMpc.solve` changes only OSQP's vectors and never returns a non-finite or
out-of-bounds input (a failed solve: the previous plan shifted, ``fallback``). Derivation,
settings and measurements: docs/mpc.md.
"""
from dataclasses import dataclass, field, replace
import functools
import math
import signal
import time
from typing import Optional, Sequence, Tuple

import numpy as np
import osqp
import scipy.sparse as sp

from metampc_common.params import param
from metampc_model.latent_model import LatentModel
from metampc_controller.planner import PlannerConfig, PlanResult
from metampc_controller.offset_free import DisturbanceEstimator, FORMS, SteadyStateTarget
from metampc_controller.terminal_cost import terminal_cost, TerminalCost

# OSQP's Ctrl-C listener takes a SIGINT that arrives during a solve (status OSQP_SIGINT,
# "Solver interrupted") and the process's own handler never sees it: a node asked to stop
# would go on. solve() gives it back to the process.
_SIGINT = int(osqp.SolverStatus.OSQP_SIGINT)
# OSQP statuses whose solution is used; 'solved inaccurate' is what a capped solve reports when
# it meets 10x the tolerances, still a good plan.
_USABLE = frozenset(int(s) for s in (osqp.SolverStatus.OSQP_SOLVED,
                                     osqp.SolverStatus.OSQP_SOLVED_INACCURATE))


# OSQP's own default time limit: no cap (it takes no 0).
NO_TIME_LIMIT = 1e10


@dataclass
class MpcConfig(PlannerConfig):
    """Settings of the latent MPC: the shared horizon, weights and bounds
    (:class:`~metampc_controller.planner.PlannerConfig`) and its own. Weights and bounds are
    in the model's physical units; why each OSQP setting has its value: docs/mpc.md (OSQP
    settings).

    Attributes:
        offset_free: disturbance form of :mod:`~metampc_controller.offset_free`, or 'none'.
        disturbance_gain: its estimator's filter gain g in (0, 1].
        y_min, y_max: soft output bounds, (n_y,) each or empty (none); +-inf leaves an output
            unbounded on that side. Planned outputs y_{t+k}, k = 1..N, may leave them only by
            a slack s >= 0 that costs soft_penalty * s (an exact penalty: with a penalty
            above the constraint's multiplier the plan meets the bounds whenever it can, and
            a plan always exists).
        soft_penalty: rho of that penalty, cost units per output unit and step.
        terminal_reg: eps of Qbar = Cbar'QCbar + eps I, relative to ||Cbar'QCbar||_2.
        max_iter: OSQP iteration cap; a capped solve is a failure (fallback), not a result.
        time_limit: OSQP run-time cap, s (wall clock): it should trip only when the machine
            stalls the process, when the input would be late anyway (online collection,
            which waits for nothing, runs without one: NO_TIME_LIMIT).
        eps_abs, eps_rel: OSQP termination tolerances.
        warm_start: start OSQP from the shifted previous plan (its duals stay OSQP's own).
        polish: OSQP polishing (an extra reduced KKT solve for an active-set-exact answer;
            when on, OSQP's C code prints to stdout despite verbose=False).
        check_termination: OSQP checks convergence every this many iterations (its default
            25 makes every solve run at least 25).
        scaling: OSQP Ruiz equilibration iterations (the condensed Hessian is badly scaled).
        adaptive_rho_interval: iterations between OSQP rho updates; fixed (not 0 = automatic
            by timing) so that iteration counts do not depend on the machine's speed.
    """

    offset_free: str = param('state', 'offset-free tracking: the integrating disturbance form '
                                      '(state: latent and output, input, output; none: eq. mpc '
                                      'as the paper writes it)', choices=FORMS, live=True)
    disturbance_gain: float = param(0.5, 'offset-free estimator gain g of p <- (1 - g) p + g '
                                         'p_inst (1: deadbeat)', gt=0, le=1, live=True)
    y_min: Sequence[float] = param((), 'soft output lower bounds, one per output (-inf: none; '
                                       'empty: no soft bounds)', item=float, live=True,
                                   infinite=True)
    y_max: Sequence[float] = param((), 'soft output upper bounds, one per output (inf: none; '
                                       'empty: no soft bounds; >= y_min)', item=float,
                                   live=True, infinite=True)
    soft_penalty: float = param(1e3, 'exact L1 penalty per unit of planned output-bound '
                                     'violation (slack), per step', gt=0, live=True)
    terminal_reg: float = 1e-6
    max_iter: int = param(500, 'OSQP iteration cap', ge=1)
    time_limit: float = param(0.05, 'OSQP wall-time cap per solve, s', gt=0)
    eps_abs: float = param(1e-4, 'OSQP absolute tolerance', gt=0)
    eps_rel: float = param(1e-4, 'OSQP relative tolerance', ge=0)
    warm_start: bool = True
    polish: bool = False
    check_termination: int = 5
    scaling: int = 10
    adaptive_rho_interval: int = 25

    def __post_init__(self):
        super().__post_init__()
        y_lo, y_hi = self.output_bounds(np.size(self.q))
        if np.any(np.isnan(y_lo)) or np.any(np.isnan(y_hi)) or np.any(y_lo > y_hi):
            raise ValueError(f'soft output bounds need y_min <= y_max, got {list(self.y_min)}, '
                             f'{list(self.y_max)}')
        if not (self.terminal_reg > 0 and self.check_termination >= 1):
            raise ValueError('need terminal_reg > 0 and check_termination >= 1')

    def output_bounds(self, n_y: int) -> Tuple[np.ndarray, np.ndarray]:
        """(y_min, y_max), each (n_y,) (-inf / inf where none); ValueError for a length that
        is neither 0 nor n_y."""
        out = []
        for name, v, none in (('y_min', self.y_min, -np.inf), ('y_max', self.y_max, np.inf)):
            v = np.asarray(v, dtype=float)
            if v.size == 0:
                v = np.full(n_y, none)
            elif v.shape != (n_y,):
                raise ValueError(f'{name} needs one value per output ({n_y}) or none, got '
                                 f'{v.tolist()}')
            out.append(v)
        return out[0], out[1]

    def osqp_settings(self) -> dict:
        """Keyword settings for osqp.OSQP.setup (osqp >= 1.0 names)."""
        return dict(verbose=False, max_iter=self.max_iter, time_limit=self.time_limit,
                    eps_abs=self.eps_abs, eps_rel=self.eps_rel,
                    warm_starting=self.warm_start, polishing=self.polish,
                    check_termination=self.check_termination, scaling=self.scaling,
                    adaptive_rho_interval=self.adaptive_rho_interval)


@dataclass
class QpSnapshot:
    """The QP of the last solve() call, min 1/2 x'Px + q'x s.t. l <= Ax <= u, and the primal
    warm start it used (None without one). For benchmarks against raw OSQP."""

    P: sp.csc_matrix
    q: np.ndarray
    A: sp.csc_matrix
    l: np.ndarray  # noqa: E741 (OSQP's name)
    u: np.ndarray
    x_warm: Optional[np.ndarray]


@dataclass
class _Problem:
    """Everything solve() needs for one (model, config), swapped as one reference.

    Per tick, with w = [z_t; u_t; r_{t+1..t+N}; e'; d'; s_ss] and m least-squares rows::

        [q; y0; b] = Gw w    q = -2 L'b: OSQP's linear cost, y0: free response of the outputs
                             (N n_y), b: target of L U (m)
        y_pred = Yu U + y0

    Stacking everything the data determine into one matrix makes the whole data-to-QP map a
    single matrix-vector product.
    """

    model: LatentModel
    terminal: TerminalCost
    solver: osqp.OSQP
    condensing: '_Condensing'
    p_x: np.ndarray        # H's upper-triangle values (_Condensing.p_matrix)
    A: sp.csc_matrix
    L: np.ndarray          # (m, N n_u)
    Gw: np.ndarray         # (N n_u + N n_y + m, n_z + n_u + N n_y + n_z + n_y + n_s)
    Yu: np.ndarray         # (N n_y, N n_u)
    lo: np.ndarray         # (N n_u,) bounds over the horizon
    hi: np.ndarray
    warm: bool             # MpcConfig.warm_start
    target: SteadyStateTarget
    estimator: Optional[DisturbanceEstimator]   # None: offset_free off
    soft: Optional['_SoftBounds']       # None: no soft output bounds
    w: np.ndarray = field(init=False)   # buffers reused every tick, and views into them
    qyb: np.ndarray = field(init=False)
    x_warm: np.ndarray = field(init=False)
    views: tuple = field(init=False)
    n_u: int = field(init=False)
    ref_shape: tuple = field(init=False)
    ext: object = None          # OSQP's compiled solver (set_solver), or None

    def __post_init__(self):
        n_z, n_u, n_y = self.model.n_z, self.model.n_u, self.model.n_y
        n, n_ny = self.lo.size, self.Yu.shape[0]
        self.n_u, self.ref_shape = n_u, (n_ny // n_y, n_y)
        self.w = np.empty(self.Gw.shape[1])
        self.qyb = np.empty(self.Gw.shape[0])
        self.x_warm = np.empty(n if self.soft is None else n + self.soft.n_s)
        # (z_t, u_t, r (N, n_y), [e'; d'], s_ss) slots of w; (q, y0, b) parts of qyb;
        # [r_{t+N}; e'; d'], the steady-state target's data.
        i_r, i_e = n_z + n_u, n_z + n_u + n_ny
        i_s = i_e + n_z + n_y
        self.views = (self.w[:n_z], self.w[n_z:i_r], self.w[i_r:i_e].reshape(self.ref_shape),
                      self.qyb[:n], self.qyb[n:n + n_ny], self.qyb[n + n_ny:],
                      self.w[i_e:i_s], self.w[i_s:], self.w[i_e - n_y:i_s])
        self.w[i_e:i_s] = np.concatenate([self.model.e, self.model.d])
        self.set_solver(self.solver, self.ext)

    def p_matrix(self) -> sp.csc_matrix:
        """OSQP's P (upper triangle of H = 2 L'L, zero rows and columns for slacks)."""
        return self.condensing.p_matrix(self.p_x, self.A.shape[1])

    def set_solver(self, solver: osqp.OSQP, ext: object = None) -> None:
        """Use this OSQP instance (set up for P, A and osqp_bounds()) from the next solve on;
        ext: its compiled solver where the caller has it (_extension(solver))."""
        self.solver, self.ext = solver, ext if ext is not None else _extension(solver)

    def osqp_bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        """OSQP's (l, u) at set-up: the input box, and with soft bounds their rows."""
        if self.soft is None:
            return self.lo, self.hi
        return self.soft.l, self.soft.u


@dataclass
class _SoftBounds:
    """The soft output bounds of one QP: slacks s (n_s,) >= 0 on the bounded outputs of every
    step, variables x = [U; s], rows [I 0; Yb I; Yb -I; 0 I] with, per tick,

        y_min - y0_b <= Yb U + s,     Yb U - s <= y_max - y0_b,     s >= 0

    (y0_b: the free response at the bounded rows). Only l, u and q change per tick."""

    rows: np.ndarray        # (n_s,) indices into y0 (N n_y) of the bounded outputs
    y_lo: np.ndarray        # (n_s,) bounds per row (-inf / inf where none)
    y_hi: np.ndarray
    l: np.ndarray           # (n + 3 n_s,) OSQP bounds, rewritten each tick
    u: np.ndarray
    q: np.ndarray           # (n + n_s,) linear cost [q_U; rho 1]
    n: int                  # N n_u

    @property
    def n_s(self) -> int:
        return self.rows.size

    def update(self, q_u: np.ndarray, y0: np.ndarray) -> None:
        """Write the tick's q, l and u from the QP's q_U and the free response y0."""
        n, n_s = self.n, self.n_s
        self.q[:n] = q_u
        y0_b = y0[self.rows]
        np.subtract(self.y_lo, y0_b, out=self.l[n:n + n_s])
        np.subtract(self.y_hi, y0_b, out=self.u[n + n_s:n + 2 * n_s])


def _soft_bounds(cfg: MpcConfig, y_u: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 n_y: int) -> tuple:
    """(_SoftBounds or None, OSQP's A) of the QP with the config's soft output bounds."""
    n = lo.size
    y_lo, y_hi = cfg.output_bounds(n_y)
    bounded = np.isfinite(y_lo) | np.isfinite(y_hi)
    if not bounded.any():
        return None, sp.identity(n, format='csc')
    steps = y_u.shape[0] // n_y
    rows = (np.arange(steps)[:, None] * n_y + np.flatnonzero(bounded)[None, :]).ravel()
    n_s = rows.size
    # OSQP's compiled update takes no inf (its Python wrapper clips it at set-up only).
    big = osqp.constant('OSQP_INFTY')
    y_lo, y_hi = np.clip(y_lo, -big, big), np.clip(y_hi, -big, big)
    yb = sp.csc_matrix(y_u[rows])
    eye_s = sp.identity(n_s, format='csc')
    A = sp.vstack([sp.hstack([sp.identity(n), sp.csc_matrix((n, n_s))]),
                   sp.hstack([yb, eye_s]), sp.hstack([yb, -eye_s]),
                   sp.hstack([sp.csc_matrix((n_s, n)), eye_s])], format='csc')
    inf = np.full(n_s, big)
    soft = _SoftBounds(rows=rows, y_lo=np.tile(y_lo, steps)[rows], y_hi=np.tile(y_hi, steps)[rows],
                       l=np.concatenate([lo, -inf, -inf, np.zeros(n_s)]),
                       u=np.concatenate([hi, inf, inf, inf]),
                       q=np.concatenate([np.zeros(n), np.full(n_s, cfg.soft_penalty)]), n=n)
    return soft, A


class LatentMpc:
    """Receding-horizon latent MPC, a :class:`~metampc_controller.planner.Planner`; call
    set_model() (outside the control tick), then solve() once per tick. solve() is not
    reentrant; set_model() may run in another thread (it swaps one reference; not with
    near=True), and the previous plan survives a model swap (it is a plan of inputs)."""

    def __init__(self, config: MpcConfig):
        self._config = config
        self._problem: Optional[_Problem] = None
        self._plan: Optional[np.ndarray] = None    # (N n_u,) last returned plan
        self._x_warm: Optional[np.ndarray] = None

    @property
    def config(self) -> MpcConfig:
        return self._config

    @property
    def terminal(self) -> Optional[TerminalCost]:
        """Terminal cost of the current model (P, DARE residual, `dare_unusable`), or None."""
        return None if self._problem is None else self._problem.terminal

    def describe_offset_free(self) -> str:
        """One line: the offset-free form in use for the model and why it may be (its rank)."""
        pb = self._problem
        est = None if pb is None else pb.estimator
        if est is None:
            return 'none (eq. (mpc) as the paper writes it)'
        dist = est.dist
        return (f'{dist.form}: n_d = {dist.n_d} disturbances, detectable (rank '
                f'[[A - I, B_d], [C, C_d]] = {dist.rank}), gain {est.gain:g}')

    def set_config(self, config: MpcConfig) -> None:
        """New settings; rebuilds the QP if a model is set. The previous plan is kept when the
        horizon is unchanged."""
        if config.horizon != self._config.horizon:
            self.reset()
        self._config = config
        if self._problem is not None:
            self.set_model(self._problem.model)

    def reset(self) -> None:
        """Start cold, as on a freshly set-up model: forget the previous plan (the next
        fallback holds u_t) and OSQP's iterates and adapted rho, so that the next solves
        depend on their own data only (a new plant episode replays exactly)."""
        self._plan = None
        pb = self._problem
        if pb is not None:
            pb.set_solver(_setup_solver(pb.p_matrix(), pb.A, *pb.osqp_bounds(), self._config))
            if pb.estimator is not None:
                pb.estimator.reset()

    def set_time_limit(self, seconds: float) -> None:
        """OSQP's wall-clock cap from the next solve on, in place: the solver keeps its warm
        start and adapted rho (a rebuilt one starts cold), and a reset keeps the cap."""
        self._config = replace(self._config, time_limit=seconds)
        if self._problem is not None:
            self._problem.solver.update_settings(time_limit=seconds)

    def set_model(self, model: LatentModel, near: bool = False) -> None:
        """Build the condensed QP, the terminal cost and the offset-free estimator for a model
        (once per model). ValueError (one line) if the model does not fit, or fails the
        offset-free form's detectability test.

        near: the model is a relinearisation of the one in use (LocalLinearMpc): where the
        QP's size is unchanged, the OSQP instance is updated in place (the new H; its iterates
        and rho kept) instead of a new one set up (~0.6 ms), the problem in use takes the new
        matrices (so: not while solve() runs; LocalLinearMpc calls both in its tick), and the
        DARE's state weight is kept where C is; the same QP either way."""
        model.validate()
        old = self._problem if near else None
        cfg = self._config
        n_z, n_u, n_y, N = model.n_z, model.n_u, model.n_y, cfg.horizon
        if old is not None and old.condensing.dims == (n_z, n_u, n_y, N):
            cond, lo, hi = old.condensing, old.lo, old.hi
        else:
            old = None
            q = np.asarray(cfg.q, dtype=float)
            if q.shape != (n_y,):
                raise ValueError(f'q has {q.size} weights, the model has {n_y} outputs')
            r, u_min, u_max = (np.broadcast_to(np.asarray(v, dtype=float), (n_u,))
                               for v in (cfg.r, cfg.u_min, cfg.u_max))
            cond = _condensing(n_z, n_u, n_y, N, tuple(q), tuple(r), True)
            lo, hi = np.tile(u_min, N), np.tile(u_max, N)
        same_c = old is not None and (old.model.C is model.C
                                      or np.array_equal(old.model.C, model.C))
        term = terminal_cost(model, cond.q, cond.r, cfg.terminal_reg,
                             old.terminal.weights if same_c else None)
        if cond.usable == term.dare_unusable:
            cond = _condensing(*cond.dims, tuple(cond.q), tuple(cond.r), not cond.usable)
        estimator = DisturbanceEstimator.of(model, cfg.offset_free, cfg.disturbance_gain)
        L, Gw, y_u, p_x = cond.matrices(model, term)
        if old is not None and old.soft is None:    # the config's: none again
            soft, cons = None, old.A
        else:
            soft, cons = _soft_bounds(cfg, y_u, lo, hi, n_y)
        if old is not None and (cons is old.A or _same_pattern(old.A, cons)):
            solver = old.solver
            if old.ext is not None:
                old.ext.update_data_mat(P_x=p_x, P_i=None,
                                        A_x=None if soft is None else cons.data, A_i=None)
            else:
                solver.update(Px=p_x, **({} if soft is None else {'Ax': cons.data}))
        else:
            solver = _setup_solver(cond.p_matrix(p_x, cons.shape[1]), cons,
                                   *((lo, hi) if soft is None else (soft.l, soft.u)), cfg)
        target = SteadyStateTarget(model, cond.q, term.ss_r, term.ss_e, lo[:n_u], hi[:n_u],
                                   bounded=estimator is not None)
        if old is not None and solver is old.solver and old.Gw.shape == Gw.shape:
            # The same sizes: the problem in use takes the new model (its buffers kept).
            old.model, old.terminal, old.condensing, old.p_x, old.A = model, term, cond, p_x, cons
            old.L, old.Gw, old.Yu, old.target, old.estimator, old.soft = (L, Gw, y_u, target,
                                                                          estimator, soft)
            old.views[6][:n_z], old.views[6][n_z:] = model.e, model.d
            return
        self._problem = _Problem(model=model, terminal=term, solver=solver, condensing=cond,
                                 p_x=p_x, A=cons, L=L, Gw=Gw, Yu=y_u, lo=lo, hi=hi,
                                 warm=bool(cfg.warm_start), target=target,
                                 estimator=estimator, soft=soft,
                                 ext=old.ext if old is not None and solver is old.solver
                                 else None)
        # The plan's size changes only with n_u, and then it says nothing about the new inputs.
        if self._plan is not None and self._plan.shape != (lo.size,):
            self.reset()

    def set_constants(self, e: np.ndarray, d: np.ndarray) -> None:
        """The constants e (n_z,) and d (n_y,) of the model in use replaced in place, nothing
        rebuilt: the QP, its terminal cost and the steady-state target's map depend on A, B, C
        only, and e, d reach each solve through the data vector. Without offset-free tracking
        (the estimator is set up with the model's constants). ValueError: no model, offset-free
        on, or shapes that differ or values that are not finite."""
        pb = self._problem
        if pb is None or pb.estimator is not None:
            raise ValueError('set_constants needs a model set up without offset-free tracking')
        model = replace(pb.model, e=np.asarray(e, dtype=float), d=np.asarray(d, dtype=float))
        model.validate()
        pb.model = model
        pb.views[6][:] = np.concatenate([model.e, model.d])

    def solve(self, z0: np.ndarray, u_prev: np.ndarray, y_ref: np.ndarray,
              y: Optional[np.ndarray] = None, step: Optional[int] = None) -> PlanResult:
        """Plan u_{t+1..t+N} from z_t (n_z,), the applied input u_t (n_u,) and the references
        r_{t+1..t+N} (N, n_y), in physical units (eq. (mpc)).

        y: the measured y_t (n_y,), which the offset-free estimator takes (with the sample's
        index `step`, so that a skipped tick is not read as one step); without it the
        disturbance estimate stays as it is. A sample it refuses (not finite) fails the tick
        as non-finite z_t does: status 'invalid data', the fallback, the estimate unchanged.

        Per call: copies into the data vector w, one finiteness check, one product
        [q; y0; b] = Gw w, OSQP (q, primal warm start, solve), the clip into the bounds, the
        prediction y_pred = Yu U + y0; nothing is rebuilt or re-sent (settings, matrices).
        """
        start = time.perf_counter()
        pb = self._problem
        if pb is None:
            raise RuntimeError('LatentMpc.solve() before set_model()')
        w_z, w_u, w_r, q, y0, b, w_ed, w_s, w_target = pb.views
        if y_ref.shape != pb.ref_shape:
            raise ValueError(f'y_ref has shape {y_ref.shape}, expected {pb.ref_shape}')
        n_u = pb.n_u
        w_z[:] = z0
        w_u[:] = u_prev
        w_r[:] = y_ref
        est = pb.estimator
        refused = 0 if est is None else est.refused
        if est is None:
            disturbance = _NO_DISTURBANCE      # w_ed holds the model's e, d (set-up)
        else:
            if y is not None:
                est.update(z0, u_prev, y, step)     # refuses (and counts) a non-finite sample
            est.constants(w_ed)
            disturbance = est.p.copy()
        # One dot product checks the data for nan/inf before they can reach the steady-state
        # target and the solver; a sample the estimator refused fails the tick alike.
        data = pb.w[:pb.w.size - w_s.size]
        valid = math.isfinite(np.dot(data, data)) and (est is None or est.refused == refused)
        if valid:
            pb.target(w_target, w_s)
            valid = math.isfinite(np.dot(w_s, w_s))
        status, iters, x, cost = 'invalid data', 0, None, math.nan
        prev = self._plan
        if valid:
            np.dot(pb.Gw, pb.w, out=pb.qyb)
            bb = float(np.dot(b, b))
            x_warm = None
            n = prev.size if prev is not None else 0
            if pb.warm and prev is not None:
                # Primal only: OSQP keeps its own duals from the last solve, which measured
                # fewer iterations than shifted duals (8 against 18 on the paper task).
                x_warm = pb.x_warm          # the previous plan shifted by one step
                x_warm[:n - n_u] = prev[n_u:]
                x_warm[n - n_u:n] = prev[-n_u:]
                x_warm[n:] = 0.0            # slacks, if any: none planned
            self._x_warm = x_warm
            soft = pb.soft
            q_osqp, l_osqp, u_osqp = q, None, None
            if soft is not None:
                soft.update(q, y0)
                q_osqp, l_osqp, u_osqp = soft.q, soft.l, soft.u
            ext = pb.ext
            if ext is not None:
                # What osqp.OSQP's update(q=), warm_start(x=) and solve() call, without the
                # wrapper's per-call extras the tick never reads (solve() copies all of OSQP's
                # info into a namespace: ~15 us, a third of a warm solve at N = 20).
                ext.update_data_vec(q_osqp, l_osqp, u_osqp)
                if x_warm is not None:
                    ext.warm_start(x_warm, None)
                ext.solve()
                info = ext.info
                # obj_val = 1/2 x'Px + q'x is non-finite iff x is; J = obj_val + b'b.
                status, iters, obj = info.status, info.iter, info.obj_val
                if info.status_val in _USABLE and math.isfinite(obj):
                    x, cost = ext.solution.x, obj + bb
            else:
                solver = pb.solver
                if soft is None:
                    solver.update(q=q)
                else:
                    solver.update(q=soft.q, l=soft.l, u=soft.u)
                if x_warm is not None:
                    solver.warm_start(x=x_warm)
                res = solver.solve(raise_error=False)
                info = res.info
                status, iters, obj = info.status, info.iter, info.obj_val
                if info.status_val in _USABLE and math.isfinite(obj):
                    x, cost = res.x, obj + bb
            if info.status_val == _SIGINT:
                signal.raise_signal(signal.SIGINT)
        fallback = x is None
        slack = 0.0
        if not fallback and pb.soft is not None:
            n = pb.lo.size
            slack = max(0.0, float(np.max(x[n:])))
            cost -= pb.soft.q[n:] @ x[n:]      # J alone; the penalty is reported as slack
            x = x[:n]
        if fallback:
            if prev is not None:
                x = _shift(prev, n_u)
            else:
                x = np.tile(np.where(np.isfinite(u_prev), u_prev, 0.0), pb.ref_shape[0])
        # OSQP meets the bounds to eps_abs only; the plant gets exactly feasible inputs.
        plan = np.maximum(x, pb.lo)
        np.minimum(plan, pb.hi, out=plan)
        plan.flags.writeable = False    # kept as the next warm start; shared with the result
        self._plan = plan
        if valid:
            y_pred = np.dot(pb.Yu, plan)
            y_pred += y0
            if fallback:
                resid = pb.L @ plan - b
                cost = float(resid @ resid)
        else:
            y_pred = np.full(pb.Yu.shape[0], math.nan)
        return PlanResult(u=plan[:n_u], u_plan=plan.reshape(-1, n_u),
                          y_pred=y_pred.reshape(pb.ref_shape), cost=cost, status=status,
                          iterations=iters, solve_time=time.perf_counter() - start,
                          fallback=fallback, terminal_fallback=pb.terminal.dare_unusable,
                          disturbance=disturbance, slack=slack)

    def last_qp(self) -> QpSnapshot:
        """Copy of the QP data of the last solve() (for benchmarks against raw OSQP)."""
        pb = self._problem
        lo, hi = pb.osqp_bounds()
        q = pb.views[3] if pb.soft is None else pb.soft.q
        return QpSnapshot(P=pb.p_matrix(), q=q.copy(), A=pb.A, l=lo.copy(), u=hi.copy(),
                          x_warm=None if self._x_warm is None else self._x_warm.copy())


_NO_DISTURBANCE = np.zeros(0)


def _setup_solver(P: sp.csc_matrix, A: sp.csc_matrix, lo: np.ndarray, hi: np.ndarray,
                  config: MpcConfig) -> osqp.OSQP:
    """A new OSQP instance of the condensed QP. q = 0 at set-up: OSQP scales the cost once from
    (P, q), so the scaling stays independent of the first tick's data."""
    # The builtin algebra named: OSQP's default looks for its MKL and CUDA modules on every
    # construction (a failed import each, ~1 ms: the locally linear MPC builds one per tick),
    # and would pick MKL where installed, so the same QP could solve differently per machine.
    solver = osqp.OSQP(algebra='builtin')
    solver.setup(P=P, q=np.zeros(P.shape[0]), A=A, l=lo, u=hi, **config.osqp_settings())
    return solver


def _same_pattern(a: sp.csc_matrix, b: sp.csc_matrix) -> bool:
    """Whether two CSC matrices have one sparsity pattern (OSQP's update takes values only)."""
    return (a.shape == b.shape and np.array_equal(a.indptr, b.indptr)
            and np.array_equal(a.indices, b.indices))


def _extension(solver: osqp.OSQP):
    """The compiled solver inside an osqp.OSQP (osqp 1.x keeps it as ``_solver``: the object
    whose update_data_vec, update_data_mat, warm_start and solve the wrapper's update,
    warm_start and solve call), or None where it lacks one of them; solve() and set_model()
    then go through the wrapper."""
    ext = getattr(solver, '_solver', None)
    calls = ('update_data_vec', 'update_data_mat', 'warm_start', 'solve', 'info', 'solution')
    if ext is None or not all(hasattr(ext, name) for name in calls):
        return None
    return ext


def _shift(v: np.ndarray, n_u: int) -> np.ndarray:
    """A stacked plan (N n_u,) advanced one step, its last input repeated."""
    return np.concatenate((v[n_u:], v[-n_u:]))


class _Condensing:
    """Eq. (mpc) condensed, J(U) = ||L U - G w||^2 with w = [z_t; u_t; r_{t+1..t+N}; e'; d';
    s_ss] (e', d' stand for the model's e, d in every row), for one size (n_z, n_u, n_y, N),
    weights (q, r) and terminal form (the DARE's n_s rows T s_N, or where it is unusable the
    tracked outputs at N as at the other steps). Rows of L: Q^{1/2}-weighted tracked outputs
    at k = 1..N-1, the terminal rows, R^{1/2} du at k = 0..N-1. With it the output prediction
    y_{t+1..t+N} = Yu U + Yw w.

    Every entry of L, G, Yu, Yw is a constant (0, weights) or one entry of a source vector
    times a constant: the model's products C A^k (k = 1..N), C sum_{i<k} A^i, C A^k B,
    T_z A^N, T_z sum_{i<N} A^i, T_z A^k B (+ T_u at k = 0), T; so a model's matrices are a
    few batched products and one scatter onto the constants, with the index map built here
    (once per size: a planner relinearising every tick condenses each tick). H = 2 L'L is
    handed to OSQP as the values of its whole upper triangle (one sparsity pattern for every
    model of the size).
    """

    def __init__(self, n_z: int, n_u: int, n_y: int, N: int, q: tuple, r: tuple,
                 usable: bool):
        self.dims, self.usable = (n_z, n_u, n_y, N), usable
        self.q, self.r = np.array(q), np.array(r)
        n, n_s = N * n_u, n_z + n_u
        i_r, i_e = n_z + n_u, n_z + n_u + N * n_y         # column offsets of r and e' in w
        i_d, i_s = i_e + n_z, i_e + n_z + n_y
        n_w = i_s + n_s
        trk = np.flatnonzero(self.q > 0)
        n_t, sq, sr = trk.size, np.sqrt(self.q[trk]), np.sqrt(self.r)
        k_t = N - 1 if usable else N                        # tracking blocks
        n_term = n_s if usable else 0
        m = k_t * n_t + n_term + n
        # Source vector: [CP (2N, n_y, n_z) | CAB (N, n_y, n_u) | TP (2, n_s, n_z) |
        # TAB (N, n_s, n_u) | T (n_s, n_s)] (the T parts with a usable DARE only); `one`
        # marks the constant entries while the map is built.
        o_cab = 2 * N * n_y * n_z
        o_tp = o_cab + N * n_y * n_u
        o_tab = o_tp + 2 * n_term * n_z
        o_t = o_tab + N * n_term * n_u
        one = o_t + n_term * n_s
        self.src_size, self.offsets = one, (o_cab, o_tp, o_tab, o_t)
        # Output buffer: [Gw = (-2 L'G (n rows); Yw; G) | L | Yu]; -2 L'G computed.
        shapes = {'top': (n, n_w), 'yw': (N * n_y, n_w), 'g': (m, n_w), 'l': (m, n),
                  'yu': (N * n_y, n)}
        self.slices, at = {}, 0
        for name, shape in shapes.items():
            self.slices[name] = (at, shape)
            at += shape[0] * shape[1]
        idx, scale = np.full(at, -1), np.zeros(at)

        def put(name, rows, cols, src, val=1.0):
            """Entries (rows, cols) of output `name` from sources src times val (broadcast)."""
            start, (_, width) = self.slices[name]
            rows, cols, src, val = np.broadcast_arrays(rows, cols, src, val)
            flat = start + rows * width + cols
            idx[flat], scale[flat] = src, val

        # Open grids over (output step k, input step j, output i, input v, latent c, ...).
        k, j, i, v = np.ix_(np.arange(N), np.arange(N), np.arange(n_y), np.arange(n_u))
        low = np.broadcast_to(j <= k, (N, N, n_y, n_u))
        # Yu: C A^(k-j) B, output step k+1, input step j <= k.
        put('yu', np.broadcast_to(k * n_y + i, low.shape)[low],
            np.broadcast_to(j * n_u + v, low.shape)[low],
            np.broadcast_to(o_cab + ((k - j) * n_y + i) * n_u + v, low.shape)[low])
        # Yw: C A^(k+1) on z_t, C (A^0 + ... + A^k) on e', I on d'.
        k, i, c = np.ix_(np.arange(N), np.arange(n_y), np.arange(n_z))
        put('yw', k * n_y + i, c, (k * n_y + i) * n_z + c)
        put('yw', k * n_y + i, i_e + c, ((N + k) * n_y + i) * n_z + c)
        k, i = np.ix_(np.arange(N), np.arange(n_y))
        put('yw', k * n_y + i, i_d + i, one)
        # Tracking rows (blocks b = 0..k_t-1, tracked output trk[t]): G's z_t, e' columns,
        # its reference and d' entries; L's C A^(b-j) B.
        b_, t, c = np.ix_(np.arange(k_t), np.arange(n_t), np.arange(n_z))
        row, out_i, w_t = b_ * n_t + t, trk[t], sq[t]
        put('g', row, c, (b_ * n_y + out_i) * n_z + c, -w_t)
        put('g', row, i_e + c, ((N + b_) * n_y + out_i) * n_z + c, -w_t)
        b_, t = np.ix_(np.arange(k_t), np.arange(n_t))
        put('g', b_ * n_t + t, i_r + b_ * n_y + trk[t], one, sq[t])
        put('g', b_ * n_t + t, i_d + trk[t], one, -sq[t])
        b_, j, t, v = np.ix_(np.arange(k_t), np.arange(N), np.arange(n_t), np.arange(n_u))
        low = np.broadcast_to(j <= b_, (k_t, N, n_t, n_u))
        put('l', np.broadcast_to(b_ * n_t + t, low.shape)[low],
            np.broadcast_to(j * n_u + v, low.shape)[low],
            np.broadcast_to(o_cab + ((b_ - j) * n_y + trk[t]) * n_u + v, low.shape)[low],
            np.broadcast_to(sq[t], low.shape)[low])
        if usable:     # T s_N: T_z A^(N-1-j) B (+ T_u at j = N-1), -T_z A^N, -T_z sum, T
            t, j, v = np.ix_(np.arange(n_s), np.arange(N), np.arange(n_u))
            put('l', k_t * n_t + t, j * n_u + v, o_tab + ((N - 1 - j) * n_s + t) * n_u + v)
            t, c = np.ix_(np.arange(n_s), np.arange(n_z))
            put('g', k_t * n_t + t, c, o_tp + t * n_z + c, -1.0)
            put('g', k_t * n_t + t, i_e + c, o_tp + (n_s + t) * n_z + c, -1.0)
            t, c = np.ix_(np.arange(n_s), np.arange(n_s))
            put('g', k_t * n_t + t, i_s + c, o_t + t * n_s + c)
        # R^{1/2} du rows (u_t enters the first).
        du, w_du = k_t * n_t + n_term + np.arange(n), np.tile(sr, N)
        put('l', du, np.arange(n), one, w_du)
        put('l', du[n_u:], np.arange(n - n_u), one, -w_du[n_u:])
        put('g', du[:n_u], n_z + np.arange(n_u), one, sr)
        constant = idx == one
        self.constants = np.where(constant, scale, 0.0)
        self.constants.flags.writeable = False
        self.at = np.flatnonzero((idx >= 0) & ~constant)
        self.src_at, self.scale_at = idx[self.at], scale[self.at]
        self.views = (shapes['top'], (self.slices['g'][0], m), (self.slices['l'][0], m),
                      self.slices['yu'][0])
        self.n_gw, self.eye = n + N * n_y + m, np.eye(n_z)
        # H's upper triangle, column by column (OSQP's CSC): its values are H.flat[triu].
        cols = np.repeat(np.arange(n), np.arange(1, n + 1))
        rows = np.concatenate([np.arange(j + 1) for j in range(n)])
        self.triu, self.p_indices = rows * n + cols, rows
        self.p_indptr = np.concatenate([[0], np.cumsum(np.arange(1, n + 1))])

    def matrices(self, model: LatentModel, term: TerminalCost) -> tuple:
        """(L (m, n), Gw = [-2 L'G; Yw; G], Yu (N n_y, n), H's upper-triangle values) of a
        model and its terminal cost (of this form: ``dare_unusable == not usable``)."""
        n_z, n_u, n_y, N = self.dims
        o_cab, o_tp, o_tab, o_t = self.offsets
        A, B, C = model.A, model.B, model.C
        # A^0..A^N by doubling, then the partial sums A^0 + ... + A^k, k = 0..N-1.
        pw = np.empty((2 * N + 1, n_z, n_z))
        pw[0], pw[1] = self.eye, A
        k = 1
        while k < N:
            step = min(k, N - k)
            np.matmul(pw[k], pw[1:step + 1], out=pw[k + 1:k + step + 1])
            k += step
        np.cumsum(pw[:N], axis=0, out=pw[N + 1:])
        src = np.empty(self.src_size)
        np.matmul(C, pw[1:], out=src[:o_cab].reshape(2 * N, n_y, n_z))
        ab = np.matmul(pw[:N], B)                                     # A^k B, k = 0..N-1
        np.matmul(C, ab, out=src[o_cab:o_tp].reshape(N, n_y, n_u))
        if self.usable:
            t_z, n_s = term.T[:, :n_z], n_z + n_u
            np.matmul(t_z, pw[N::N], out=src[o_tp:o_tab].reshape(2, n_s, n_z))   # A^N, sum
            tab = src[o_tab:o_t].reshape(N, n_s, n_u)
            np.matmul(t_z, ab, out=tab)
            tab[0] += term.T[:, n_z:]
            src[o_t:] = term.T.ravel()
        out = self.constants.copy()
        vals = src[self.src_at]
        vals *= self.scale_at
        out[self.at] = vals
        (n, n_w), (g, g_rows), (l_at, m), yu = self.views
        L = out[l_at:l_at + m * n].reshape(m, n)
        Gw = out[:self.n_gw * n_w].reshape(self.n_gw, n_w)
        np.matmul(L.T, out[g:g + g_rows * n_w].reshape(g_rows, n_w), out=Gw[:n])
        Gw[:n] *= -2.0
        hess_x = (L.T @ L).ravel()[self.triu]
        hess_x *= 2.0
        return L, Gw, out[yu:yu + N * n_y * n].reshape(N * n_y, n), hess_x

    def p_matrix(self, p_x: np.ndarray, size: int) -> sp.csc_matrix:
        """OSQP's P (size, size) from H's upper-triangle values (matrices()): H in the top
        left block, zeros (stored: one pattern whatever the values) elsewhere."""
        n = self.p_indptr.size - 1
        indptr = np.concatenate([self.p_indptr, np.full(size - n, self.p_indptr[-1])])
        return sp.csc_matrix((p_x, self.p_indices, indptr), shape=(size, size))


@functools.lru_cache(maxsize=32)
def _condensing(n_z: int, n_u: int, n_y: int, N: int, q: tuple, r: tuple,
                usable: bool) -> _Condensing:
    """The condensing of one size, weights and terminal form (built once, shared)."""
    return _Condensing(n_z, n_u, n_y, N, q, r, usable)
