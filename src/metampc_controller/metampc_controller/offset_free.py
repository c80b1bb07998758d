"""Offset-free tracking for the latent MPC: integrating disturbances and the steady-state target.

The MPC of eq. (mpc) plans with the affine latent model z_{k+1} = A z_k + B u_{k+1} + e,
y_k = C z_k + d; a constant disturbance p (n_d,) augments it (+ B_d p, + C_d p; Pannocchia &
Rawlings 2003) in one of the forms 'state' (p = [w; v], n_d = n_z + n_y), 'input' (B_d = B)
or 'output' (C_d = I) of ``MpcConfig.offset_free`` ('none': eq. (mpc) as the paper writes it).
Each tick p is estimated from the one-step residuals (p <- (1 - g) p + g H^+ rho_t,
g = ``disturbance_gain``) and the terminal cost is centred on the steady state of the
corrected model that best meets the reference within the input bounds. Refuses
(:func:`disturbance_model`, ValueError naming the rank and the reason) a model whose augmented
system is not detectable. Derivation, tests and measurements: docs/mpc.md#offset-free-tracking.
"""
from dataclasses import dataclass
import math
from typing import Optional

import numpy as np
from scipy.optimize import lsq_linear

from metampc_model.latent_model import LatentModel

FORMS = ('none', 'state', 'input', 'output')
# Singular values below this (relative to the largest) count as zero in the rank test; an
# eigenvalue of A within ~1e-9 of 1 is "at 1" (a learned A never lands there by chance).
RANK_RTOL = 1e-9


@dataclass(frozen=True)
class DisturbanceModel:
    """The disturbance of one form for one model.

    Attributes:
        form: one of FORMS other than 'none'.
        Bd: (n_z, n_d) disturbance into the latent dynamics.
        Cd: (n_y, n_d) disturbance onto the outputs.
        measures_z: the estimator uses the encoder's z_t as a measurement.
        H_pinv: (n_d, n_z + n_y) map from the one-step residuals to p (zero columns for
            the residuals a form does not measure).
        rank: rank of the detectability matrix (= n_z + n_d: it passed).
    """

    form: str
    Bd: np.ndarray
    Cd: np.ndarray
    measures_z: bool
    H_pinv: np.ndarray
    rank: int

    @property
    def n_d(self) -> int:
        return self.Bd.shape[1]


def detectability_rank(A: np.ndarray, C_m: np.ndarray, Bd: np.ndarray,
                       Cdm: np.ndarray) -> int:
    """rank [[A - I, B_d], [C_m, C_dm]] (numerical, relative tolerance RANK_RTOL)."""
    n_z = A.shape[0]
    mat = np.block([[A - np.eye(n_z), Bd], [C_m, Cdm]])
    sv = np.linalg.svd(mat, compute_uv=False)
    return int(np.sum(sv > RANK_RTOL * max(sv[0], 1e-300)))


def disturbance_model(model: LatentModel, form: str) -> DisturbanceModel:
    """The disturbance of `form` for `model`, checked for detectability.

    Raises:
        ValueError: the form is unknown, or the augmented system is not detectable (one line
            with the rank and, where A has an eigenvalue at 1, that eigenvalue).
    """
    n_z, n_u, n_y = model.n_z, model.n_u, model.n_y
    if form == 'state':
        Bd = np.hstack([np.eye(n_z), np.zeros((n_z, n_y))])
        Cd = np.hstack([np.zeros((n_y, n_z)), np.eye(n_y)])
        measures_z = True
    elif form == 'input':
        Bd, Cd, measures_z = model.B.copy(), np.zeros((n_y, n_u)), True
    elif form == 'output':
        Bd, Cd, measures_z = np.zeros((n_z, n_y)), np.eye(n_y), False
    else:
        raise ValueError(f'offset_free must be one of {", ".join(FORMS[1:])} here, got {form!r}')
    n_d = Bd.shape[1]
    if measures_z:
        C_m = np.vstack([np.eye(n_z), model.C])
        Cdm = np.vstack([np.zeros((n_z, n_d)), Cd])
    else:
        C_m, Cdm = model.C, Cd
    rank = detectability_rank(model.A, C_m, Bd, Cdm)
    if rank < n_z + n_d:
        eig = np.linalg.eigvals(model.A)
        at_one = eig[np.abs(eig - 1.0) < 1e-6]
        why = (f' (A has an eigenvalue at {at_one[0].real:.6g}: that mode and the disturbance '
               'cannot be told apart)' if at_one.size else '')
        raise ValueError(f'offset_free {form}: the disturbance model is not detectable, rank '
                         f'[[A - I, B_d], [C, C_d]] = {rank} < n_z + n_d = {n_z + n_d}{why}')
    H = np.vstack([Bd, model.C @ Bd + Cd])
    if not measures_z:
        H[:n_z] = 0.0      # the latent residual is not a measurement of this form
    return DisturbanceModel(form, Bd, Cd, measures_z, np.linalg.pinv(H), rank)


class DisturbanceEstimator:
    """The integrating estimate p of one model (module docstring), and the corrected constants.

    update() once per tick of an episode, in order; reset() at a new episode. Per update two
    small matrix-vector products: p_inst = K_m [z_t; y_t] - K_p [z_{t-1}; u_t] - k with
    K_m = H^+, K_p = H^+ [[A, B], [C A, C B]], k = H^+ [e; C e + d] (precomputed).
    """

    def __init__(self, model: LatentModel, dist: DisturbanceModel, gain: float):
        self.model, self.dist, self.gain = model, dist, gain
        n_z, n_u, n_y = model.n_z, model.n_u, model.n_y
        self.p = np.zeros(dist.n_d)
        pred = np.block([[model.A, model.B], [model.C @ model.A, model.C @ model.B]])
        self._k_meas = dist.H_pinv
        self._k_pred = dist.H_pinv @ pred
        self._k_const = dist.H_pinv @ np.concatenate([model.e, model.C @ model.e + model.d])
        self._meas = np.empty(n_z + n_y)         # [z_t; y_t]
        self._prev = np.empty(n_z + n_u)         # [z_{t-1}; u_t]
        self._p_inst = np.empty(dist.n_d)
        self._n_z = n_z
        self._have_prev = False
        self._step: Optional[int] = None
        # [e'; d'] = [e; d] + [B_d; C_d] p
        self._const = np.concatenate([model.e, model.d])
        self._dist_map = np.vstack([dist.Bd, dist.Cd])

    def reset(self) -> None:
        """A new episode: p = 0, no previous latent state."""
        self.p[:] = 0.0
        self._have_prev, self._step = False, None

    def update(self, z: np.ndarray, u: np.ndarray, y: np.ndarray,
               step: Optional[int] = None) -> np.ndarray:
        """Take tick t's z_t (n_z,), applied u_t (n_u,), measured y_t (n_y,); returns p (n_d,).

        `step`: the sample's index; when it does not follow the previous update's (a tick was
        skipped) the residual would span two steps, so p is kept and only z_t is stored.
        Non-finite data leave p unchanged.
        """
        n_z, prev = self._n_z, self._prev
        if self._have_prev and (step is None or self._step is None or step == self._step + 1):
            meas, p_inst = self._meas, self._p_inst
            meas[:n_z] = z
            meas[n_z:] = y
            prev[n_z:] = u
            np.dot(self._k_meas, meas, out=p_inst)
            p_inst -= np.dot(self._k_pred, prev)
            p_inst -= self._k_const
            if math.isfinite(np.dot(p_inst, p_inst)):
                p_inst -= self.p
                p_inst *= self.gain
                self.p += p_inst
        self._have_prev = math.isfinite(np.dot(z, z))
        if self._have_prev:
            prev[:n_z] = z
        self._step = step
        return self.p

    def constants(self, out: np.ndarray) -> np.ndarray:
        """[e + B_d p (n_z,); d + C_d p (n_y,)], the corrected model's constants, into `out`."""
        np.dot(self._dist_map, self.p, out=out)
        out += self._const
        return out


class SteadyStateTarget:
    """s_s = [z_s; u_s] of the (corrected) model for a terminal reference (module docstring).

    ss_r (n_s, n_y), ss_e (n_s, n_z): the unconstrained target s = ss_r (r - d') + ss_e e'
    (terminal_cost's KKT map), computed as ss_r r + T_c [e'; d'] with T_c = [ss_e, -ss_r].
    bounded: keep u_s within [u_min, u_max] (box least squares when the unconstrained u_s
    leaves them).
    """

    def __init__(self, model: LatentModel, q: np.ndarray, ss_r: np.ndarray, ss_e: np.ndarray,
                 u_min: np.ndarray, u_max: np.ndarray, bounded: bool):
        self.ss_r = ss_r
        self._t_const = np.hstack([ss_e, -ss_r])
        self.bounded = bounded
        self._box = list(zip(u_min.tolist(), u_max.tolist()))
        self.u_min, self.u_max = u_min, u_max
        n_z = model.n_z
        self._n_z, self._n_y = n_z, model.n_y
        tracked = q > 0
        self._sq = np.sqrt(q[tracked])
        self._c_t = model.C[tracked]
        self._tracked = tracked
        # z_s = (I - A)^{-1} (B u + e'): exact when I - A is invertible; otherwise the box
        # case clips u_s and solves the equality in least squares.
        ima = np.eye(n_z) - model.A
        self._ima = ima
        self._gain = None
        if np.linalg.cond(ima) < 1e10:
            self._ima_inv = np.linalg.inv(ima)
            self._gain = self._c_t @ self._ima_inv @ model.B       # (n_tracked, n_u)
        self._B = model.B

    def __call__(self, r_n: np.ndarray, const: np.ndarray, out: np.ndarray) -> np.ndarray:
        """s_s (n_s,) into `out` for terminal reference r_n (n_y,) and the constants
        const = [e' (n_z); d' (n_y)]. Non-finite data give a non-finite s_s (solve() falls
        back on it)."""
        np.dot(self._t_const, const, out=out)
        out += np.dot(self.ss_r, r_n)
        if not self.bounded:
            return out
        u = out[self._n_z:].tolist()
        if all(lo - 1e-12 <= v <= hi + 1e-12 for v, (lo, hi) in zip(u, self._box)):
            return out
        if not all(map(math.isfinite, u)):
            return out
        e, d = const[:self._n_z], const[self._n_z:]
        if self._gain is not None:
            free = self._ima_inv @ e                 # z_s at u = 0
            target = self._sq * (r_n[self._tracked] - d[self._tracked] - self._c_t @ free)
            u_s = lsq_linear(self._sq[:, None] * self._gain, target,
                             bounds=(self.u_min, self.u_max)).x
            z_s = free + self._ima_inv @ (self._B @ u_s)
        else:
            u_s = np.clip(u, self.u_min, self.u_max)
            z_s = np.linalg.lstsq(self._ima, self._B @ u_s + e, rcond=None)[0]
        out[:self._n_z] = z_s
        out[self._n_z:] = u_s
        return out
