"""The latent MPC on a nonlinear one-step model, linearised at the current state every tick.

One QP per tick (eq. (mpc): :class:`~metampc_controller.mpc.LatentMpc`, its DARE terminal cost,
Delta-u weight and bounds) on the affine model exact to first order at (s_t, u_t): any model
with ``linearise(s, u) -> LatentModel`` (the feature NARX). The offset-free estimator would
restart with every model, so this planner plans with offset_free 'none'. A linearisation that
is not finite, or that the QP refuses, leaves the tick to the shifted previous plan (held u_t
at first), counted in ``failed_linearisations``. Why the current state: docs/nonlinear.md.
"""
from dataclasses import replace
import math
import time
from typing import Optional, Protocol

import numpy as np

from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.planner import PlanResult

LINEARISATION_FAILED = 'linearisation failed'


class LocallyLinear(Protocol):
    """A model the planner can linearise: state s (n_s,), next input u (n_u,)."""

    def linearise(self, s: np.ndarray, u_next: np.ndarray) -> LatentModel:
        """The affine model exact to first order at (s, u_next); ValueError if none."""


class LocalLinearMpc:
    """The planner of the module docstring (the :class:`~metampc_controller.planner.Planner`
    protocol, with ``state`` the model's physical s_t)."""

    def __init__(self, config: MpcConfig, model: LocallyLinear, rebuild_tol: float = 0.0):
        """rebuild_tol: the QP is set up again (DARE, condensing, OSQP) only when an entry of
        A or B moved by more than this (relative to the largest entry of the model in use);
        otherwise the new constant e alone is written into the data (LatentMpc.set_constants).
        0: a new QP every tick."""
        if not rebuild_tol >= 0:
            raise ValueError(f'rebuild_tol must be >= 0, got {rebuild_tol}')
        self._mpc = LatentMpc(replace(config, offset_free='none'))
        self.model = model
        self.rebuild_tol = rebuild_tol
        self.failed_linearisations = 0
        self.rebuilds = 0
        self._plan: Optional[np.ndarray] = None
        self._built: Optional[LatentModel] = None

    @property
    def config(self) -> MpcConfig:
        return self._mpc.config

    def reset(self) -> None:
        self._mpc.reset()
        self._plan = None
        self._built = None

    def set_time_limit(self, seconds: float) -> None:
        self._mpc.set_time_limit(seconds)

    def solve(self, state: Optional[np.ndarray], u_prev: np.ndarray, y_ref: np.ndarray,
              y: Optional[np.ndarray] = None, step: Optional[int] = None) -> PlanResult:
        """Linearise at (s_t, u_t), set the QP up, solve (module docstring)."""
        start = time.perf_counter()
        try:
            # One dot product each finds a nan or inf (or a value beyond 1e154).
            if state is None or not math.isfinite(np.dot(state, state) + np.dot(u_prev, u_prev)):
                raise ValueError('state or input not finite')
            self._set(self.model.linearise(np.asarray(state, float),
                                           np.asarray(u_prev, float)))
        except (ValueError, np.linalg.LinAlgError):
            self.failed_linearisations += 1
            return self._shifted(u_prev, y_ref, start)
        res = self._mpc.solve(state, u_prev, y_ref, y, step)
        self._plan = np.asarray(res.u_plan).reshape(-1)
        res.solve_time = time.perf_counter() - start
        return res

    def _set(self, lin: LatentModel) -> None:
        """Plan on `lin` from now on: its constants only, where A and B are those of the QP
        in use within rebuild_tol, else a new QP."""
        built = self._built
        if built is not None and built.A.shape == lin.A.shape and built.B.shape == lin.B.shape:
            if self.rebuild_tol == 0.0:
                same = (lin.A == built.A).all() and (lin.B == built.B).all()
            else:
                scale = self.rebuild_tol * max(np.max(np.abs(built.A)), np.max(np.abs(built.B)))
                same = (np.max(np.abs(lin.A - built.A)) <= scale
                        and np.max(np.abs(lin.B - built.B)) <= scale)
            if same:
                self._mpc.set_constants(lin.e, lin.d)
                return
        self._built = None
        self._mpc.set_model(lin, near=built is not None)
        self._built = lin
        self.rebuilds += 1

    def _shifted(self, u_prev: np.ndarray, y_ref: np.ndarray, start: float) -> PlanResult:
        """The shifted previous plan (held u_t, or 0 where it is not finite, at first)."""
        n_u, horizon = np.size(u_prev), y_ref.shape[0]
        lo, hi = self._mpc.config.bounds(n_u)
        if self._plan is not None:
            plan = np.concatenate([self._plan[n_u:], self._plan[-n_u:]])
        else:
            held = np.where(np.isfinite(u_prev), u_prev, 0.0)
            plan = np.tile(held, horizon)
        plan = np.clip(plan, np.tile(lo, horizon), np.tile(hi, horizon))
        plan.flags.writeable = False
        self._plan = plan
        u_plan = plan.reshape(-1, n_u)
        return PlanResult(u=u_plan[0], u_plan=u_plan, y_pred=np.full(y_ref.shape, np.nan),
                          cost=float('nan'), status=LINEARISATION_FAILED, iterations=0,
                          solve_time=time.perf_counter() - start, fallback=True)


__all__ = ['LINEARISATION_FAILED', 'LocallyLinear', 'LocalLinearMpc']
