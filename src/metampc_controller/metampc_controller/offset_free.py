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
import itertools
import math
from typing import Optional

import numpy as np
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
        self.refused = 0        # samples refused (not finite), over the estimator's life
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

    @classmethod
    def of(cls, model: LatentModel, form: str, gain: float) -> Optional['DisturbanceEstimator']:
        """The estimator of `model` in offset-free `form` with gain `gain` (None: form
        'none'); ValueError (:func:`disturbance_model`) for a model that fails its rank test.
        The one constructor of the MPC's estimator and the model check's."""
        return None if form == 'none' else cls(model, disturbance_model(model, form), gain)

    def reset(self) -> None:
        """A new episode: p = 0, no previous latent state."""
        self.p[:] = 0.0
        self._have_prev, self._step = False, None

    def update(self, z: np.ndarray, u: np.ndarray, y: np.ndarray,
               step: Optional[int] = None) -> np.ndarray:
        """Take tick t's z_t (n_z,), applied u_t (n_u,), measured y_t (n_y,); returns p (n_d,).

        `step`: the sample's index; when it does not follow the previous update's (a tick was
        skipped) the residual would span two steps, so p is kept and only z_t is stored.
        A sample with a non-finite value (or a residual too large to be finite) is refused:
        p unchanged, counted in ``refused``; a finite z_t is still kept for the next residual.
        """
        n_z, prev = self._n_z, self._prev
        z_finite = math.isfinite(np.dot(z, z))
        finite = z_finite and math.isfinite(np.dot(u, u) + np.dot(y, y))
        if not finite:
            self.refused += 1
        elif self._have_prev and (step is None or self._step is None
                                  or step == self._step + 1):
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
            else:
                self.refused += 1
        self._have_prev = z_finite
        if z_finite:
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

    Data x = [r (n_y); e' (n_z); d' (n_y)]: the terminal reference and the corrected model's
    constants, as they lie in the latent MPC's data vector. ss_r (n_s, n_y), ss_e (n_s, n_z):
    the unconstrained target s = ss_r (r - d') + ss_e e' (terminal_cost's KKT map).
    bounded: where the unconstrained u_s leaves [u_min, u_max], u_s solves the box least squares

        min_u ||W (G u - t)||^2,  u_min <= u <= u_max,   G = C_t (I - A)^{-1} B,
        t = r_t - d'_t - C_t (I - A)^{-1} e',  W = diag(sqrt(q_t))  (t: the tracked outputs),

    and z_s = (I - A)^{-1} (B u_s + e'). Solved exactly over the active sets, each input free,
    at u_min or at u_max (3^n_u sets: 9 for the tank's two pumps). With M = G'W^2G and
    h = G'W^2 t, a set's candidate is u_F = M_FF^{-1} (h_F - M_FB u_B), its gradient
    g = M u - h; it is the minimiser iff it meets the KKT conditions (free inputs within the
    box, g_i >= 0 at u_min, g_i <= 0 at u_max; convex problem). Every candidate, its s_s and
    its KKT slacks (g_i / M_ii: in input units) are affine in x, so one map built at set-up
    gives them all in one product per call, the unconstrained target first; the answer is the
    unconstrained target when within the box (to 1e-12), else the candidate whose smallest
    slack is largest (>= 0 up to rounding: the minimiser). Some set with an invertible M_FF
    holds a minimiser (one at a vertex of the set of minimisers where M is singular), so sets
    whose M_FF has a relative condition above 1e12 are left out, and those that hold an input
    at an infinite bound. The answer is the one of an
    exact box least-squares solver (scipy's BVLS; test_offset_free) at a few microseconds.
    """

    def __init__(self, model: LatentModel, q: np.ndarray, ss_r: np.ndarray, ss_e: np.ndarray,
                 u_min: np.ndarray, u_max: np.ndarray, bounded: bool):
        self._t_x = np.hstack([ss_r, ss_e, -ss_r])                 # s = T_x x
        self.bounded = bounded
        self.u_min, self.u_max = u_min, u_max
        n_z, n_y = model.n_z, model.n_y
        self._n_z, self._n_y = n_z, n_y
        # z_s = (I - A)^{-1} (B u + e'): exact when I - A is invertible; otherwise the box
        # case clips u_s and solves the equality in least squares.
        ima = np.eye(n_z) - model.A if bounded else None
        self._ima, self._B = ima, model.B
        self._map = None
        if bounded and np.linalg.cond(ima) < 1e10:
            self._map, self._offset = self._candidate_map(model, q, ima, u_min, u_max)
            # Per call, into one buffer: each candidate's s_s and slacks (views kept).
            n_s = n_z + model.n_u
            self._v = np.empty(self._offset.size)
            per = self._v.reshape(-1, n_s + 2 * model.n_u)
            self._cands, self._slacks = list(per[:, :n_s]), per[:, n_s:]
            self._worst = np.empty(per.shape[0])

    def _candidate_map(self, model: LatentModel, q: np.ndarray, ima: np.ndarray,
                       u_min: np.ndarray, u_max: np.ndarray) -> tuple:
        """(M (n_c m, n_y + n_z + n_y), o (n_c m,)): m = n_s + 2 n_u rows per candidate,
        [s_s; KKT slacks] = M x + o, the unconstrained target first, then the active sets
        with an invertible M_FF (class docstring)."""
        n_z, n_u, n_y = model.n_z, model.n_u, model.n_y
        tracked = q > 0
        ima_inv = np.linalg.inv(ima)
        ima_inv_b = ima_inv @ model.B                               # (n_z, n_u)
        gain = model.C[tracked] @ ima_inv_b                         # G (n_tracked, n_u)
        gw = gain.T * q[tracked]                                    # G'W^2 (n_u, n_tracked)
        m = gw @ gain
        scale = 1.0 / np.maximum(np.diag(m), 1e-300)               # g_i / M_ii: input units
        # h = K x, e' = E x
        k_r = np.zeros((n_u, n_y))
        k_r[:, tracked] = gw
        k_x = np.hstack([k_r, -gw @ model.C[tracked] @ ima_inv, -k_r])
        e_sel = np.hstack([np.zeros((n_z, n_y)), np.eye(n_z), np.zeros((n_z, n_y))])
        box = np.r_[-u_min, u_max]
        # The unconstrained target and its slacks u - u_min, u_max - u.
        sign = np.vstack([np.eye(n_u), -np.eye(n_u)])
        rows = [np.vstack([self._t_x, sign @ self._t_x[n_z:]])]
        offsets = [np.r_[np.zeros(n_z + n_u), box]]
        for code in itertools.product((0, 1, 2), repeat=n_u):     # free, at u_min, at u_max
            code = np.array(code)
            free = code == 0
            fixed = np.where(code == 1, u_min, u_max)[~free]
            if not np.all(np.isfinite(fixed)):          # an input at an infinite bound
                continue
            t_a, c_a = np.zeros((n_u, n_u)), np.zeros(n_u)          # u = T_a h + c_a
            c_a[~free] = fixed
            if free.any():
                m_ff = m[np.ix_(free, free)]
                if np.linalg.cond(m_ff) > 1e12:
                    continue
                inv = np.linalg.inv(m_ff)
                t_a[np.ix_(free, free)] = inv
                c_a[free] = -inv @ m[np.ix_(free, ~free)] @ fixed
            # Slacks: a free input's u - u_min and u_max - u; a fixed one's +-g_i / M_ii,
            # twice, so that every candidate has 2 n_u of them.
            slack_u = np.where(free, 1.0, 0.0)
            slack_g = np.where(code == 1, scale, np.where(code == 2, -scale, 0.0))
            s_u = np.vstack([np.diag(slack_u), -np.diag(slack_u)])
            s_g = np.vstack([np.diag(slack_g), np.diag(slack_g)])
            # [z; u; slacks] = P_h h + P_e e' + p_0
            p_h = np.vstack([ima_inv_b @ t_a, t_a, s_u @ t_a + s_g @ (m @ t_a - np.eye(n_u))])
            p_e = np.vstack([ima_inv, np.zeros((3 * n_u, n_z))])
            rows.append(p_h @ k_x + p_e @ e_sel)
            offsets.append(np.r_[ima_inv_b @ c_a, c_a, s_u @ c_a + s_g @ (m @ c_a)
                                 + np.where(np.r_[free, free], box, 0.0)])
        return np.vstack(rows), np.concatenate(offsets)

    def __call__(self, x: np.ndarray, out: np.ndarray) -> np.ndarray:
        """s_s (n_s,) into `out` for the data x = [r (n_y); e' (n_z); d' (n_y)]. Non-finite
        data give a non-finite s_s (solve() falls back on it)."""
        if self._map is None:
            np.dot(self._t_x, x, out=out)
            if self.bounded:
                self._clipped(out, x[self._n_y:self._n_y + self._n_z])
            return out
        v, worst = self._v, self._worst
        np.dot(self._map, x, out=v)
        v += self._offset
        np.minimum.reduce(self._slacks, axis=1, out=worst)
        out[:] = self._cands[0 if worst[0] >= -1e-12 else 1 + int(worst[1:].argmax())]
        return out

    def _clipped(self, out: np.ndarray, e: np.ndarray) -> None:
        """I - A singular (an integrating latent mode): a finite u_s beyond the box (1e-12)
        clipped into it, z_s from (I - A) z_s = B u_s + e' in least squares, into `out`."""
        n_z = self._n_z
        u = out[n_z:]
        if not np.all(np.isfinite(u)) or np.all((u >= self.u_min - 1e-12)
                                                & (u <= self.u_max + 1e-12)):
            return
        u_s = np.clip(u, self.u_min, self.u_max)
        out[:n_z] = np.linalg.lstsq(self._ima, self._B @ u_s + e, rcond=None)[0]
        out[n_z:] = u_s
