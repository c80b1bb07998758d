"""Terminal cost of the latent MPC: the DARE weight P of eq. (mpc), made consistent.

The state is augmented with the previous input, s_k = [z_k; u_k] (n_s = n_z + n_u), so that du_k =
u_{k+1} - u_k is the input of a linear system (Abar = [[A, B], [0, I]], Bbar = [[B], [I]], Cbar =
[C, 0]); P is the stabilising solution of the paper's DARE posed for (Abar, Bbar, Qbar = Cbar' Q
Cbar + eps I, R) rather than eq. (compact)'s state, and the terminal cost (s_N - s_ss)' P (s_N -
s_ss) is centred on the steady state s_ss that best meets r_N (affine in r_N, from the KKT matrix).
When the DARE fails (no stable deflating subspace, non-finite or non-definite P, residual above
``DARE_RTOL``, unstable closed loop) it falls back to the stage output term (P = Cbar' Q Cbar) and
says why. Both are stored as least-squares rows (P = T'T). The DARE by the QZ method in a few
LAPACK calls (:func:`dare`: a planner relinearising every tick solves one per tick). Derivation
and checks: docs/mpc.md#terminal-cost-a-consistent-dare.
"""
from dataclasses import dataclass
import functools
import math
from typing import Optional

import numpy as np
from scipy.linalg import lapack

from metampc_model.latent_model import LatentModel

# A stabilising DARE solution of a well-posed problem meets ~1e-12; 1e-6 only rejects garbage.
DARE_RTOL = 1e-6
# Below this the steady state's KKT matrix counts as singular (the pseudo-inverse's cut-off,
# eps max(m, n) relative, lies beyond it for the sizes here).
KKT_RCOND = 1e-13


@dataclass
class TerminalCost:
    """Terminal weight of eq. (mpc) on s_N = [z_N; u_N].

    Attributes:
        P: (n_s, n_s) terminal weight (DARE solution, or Cbar' Q Cbar when the DARE is unusable).
        T: (m, n_s) factor with P = T' T (m = n_s, or the number of tracked outputs).
        M: (m, n_y) with `dare_unusable` only: map from the terminal reference offset r_N - d
            to the target of T s_N (zeros with the DARE, whose target is T s_ss).
        ss_r: (n_s, n_y), ss_e: (n_s, n_z): the steady state s_ss = ss_r (r_N - d) + ss_e e
            (affine in the model's constants, so a corrected e or d moves it exactly).
        dare_unusable: True when the DARE was unusable and the output weight is used instead
            (``MpcStatus.terminal_fallback``).
        residual: relative DARE residual ||DARE(P)||_F / ||P||_F (nan if no solution).
        reason: why the DARE was unusable ('' otherwise).
        weights: (Cbar'QCbar, Qbar), (n_s, n_s) each, for the next model with the same C
            (terminal_cost).
    """

    P: np.ndarray
    T: np.ndarray
    M: np.ndarray
    ss_r: np.ndarray
    ss_e: np.ndarray
    dare_unusable: bool
    residual: float
    reason: str
    weights: tuple


@functools.lru_cache(maxsize=16)
def _constant_parts(n_z: int, n_u: int, n_y: int) -> tuple:
    """The constant parts of one size (copied, then the model's blocks written in): [Abar |
    Bbar] (n_s, n_s + n_u) with its identities, Cbar (n_y, n_s) zero, the steady state's KKT
    matrix (with -I where A - I goes) and right-hand side (:func:`_steady_state_map`), and
    LAPACK dgelsd's work sizes for it."""
    n_s = n_z + n_u
    ab = np.zeros((n_s, n_s + n_u))
    ab[n_z:, n_z:n_s] = ab[n_z:, n_s:] = np.eye(n_u)
    kkt = np.zeros((n_s + n_z, n_s + n_z))
    kkt[n_s:, :n_z] = -np.eye(n_z)
    rhs = np.zeros((n_s + n_z, n_y + n_z))
    rhs[n_s:, n_y:] = -np.eye(n_z)
    lwork = lapack.dgelsd_lwork(n_s + n_z, n_s + n_z, n_y + n_z, -1)
    parts = (ab, np.zeros((n_y, n_s)), kkt, rhs)
    for part in parts:
        part.flags.writeable = False
    return (*parts, (int(lwork[0]), int(lwork[1])))


@functools.lru_cache(maxsize=16)
def _pencil(n: int) -> np.ndarray:
    """[L | M] (2n, 4n) of :func:`dare`'s pencil, its identities in place (copied per use)."""
    pencil = np.zeros((2 * n, 4 * n))
    pencil[:n, :n] = pencil[n:, 3 * n:] = np.eye(n)
    pencil.flags.writeable = False
    return pencil


def augmented(model: LatentModel) -> tuple:
    """([Abar | Bbar] (n_s, n_s + n_u), Cbar (n_y, n_s)) of the Delta-u system."""
    n_z, n_s = model.n_z, model.n_z + model.n_u
    parts = _constant_parts(n_z, model.n_u, model.n_y)
    ab, c_bar = parts[0].copy(), parts[1].copy()
    ab[:n_z, :n_z] = model.A
    ab[:n_z, n_z:n_s] = ab[:n_z, n_s:] = model.B
    c_bar[:, :n_z] = model.C
    return ab, c_bar


def _outside(alphar: float, alphai: float, beta: float) -> bool:
    """LAPACK's select: the generalised eigenvalue (alphar + i alphai) / beta outside the unit
    circle (infinite included)."""
    return alphar * alphar + alphai * alphai > beta * beta


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^{-1} b by LAPACK's dgesv (numpy's solve without its wrapper's cost); LinAlgError where
    a is singular."""
    x, info = lapack.dgesv(a, b)[2:]
    if info != 0:
        raise np.linalg.LinAlgError(f'singular matrix (LAPACK dgesv info {info})')
    return x


def dare(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The stabilising solution P (n, n) of P = A'PA - A'PB (R + B'PB)^{-1} B'PA + Q, R = diag(r)
    (r (m,) > 0), by the QZ method: the deflating subspace [U1; U2] of the symplectic pencil
    [[A, 0], [-Q, I]] - lambda [[I, B R^{-1} B'], [0, A']] for its n eigenvalues inside the unit
    circle gives P = U2 U1^{-1}. LAPACK's dgges on the reciprocal pencil, ordered by its select
    (those outside the unit circle first), which its QZ iteration mostly leaves to few swaps.
    LinAlgError where the pencil has not n such eigenvalues (not stabilisable, or eigenvalues on
    the unit circle) or QZ fails; the caller checks the answer (terminal_cost)."""
    n = a.shape[0]
    pencil = _pencil(n).copy()
    pencil[:n, n:2 * n] = (b / r) @ b.T
    pencil[n:, n:2 * n] = a.T
    pencil[:n, 2 * n:3 * n] = a
    np.negative(q, out=pencil[n:, 2 * n:3 * n])
    out = lapack.dgges(_outside, pencil[:, :2 * n], pencil[:, 2 * n:], jobvsl=0, sort_t=1,
                       overwrite_a=1, overwrite_b=1)
    sdim, u, info = out[2], out[7], out[-1]
    if info != 0 or sdim != n:
        raise np.linalg.LinAlgError(f'the symplectic pencil has {sdim} of {n} eigenvalues '
                                    f'inside the unit circle (LAPACK info {info})')
    p = _solve(u[:n, :n].T, u[n:, :n].T)            # P' = U1^{-T} U2'
    return 0.5 * (p + p.T)


def terminal_cost(model: LatentModel, q: np.ndarray, r: np.ndarray, reg: float,
                  weights: Optional[tuple] = None) -> TerminalCost:
    """Terminal cost for output weights q (n_y,) >= 0, Delta-u weights r (n_u,) > 0.

    reg: relative eps of the state-weight regularisation Qbar = Cbar'QCbar + eps I.
    weights: (Cbar'QCbar, Qbar) where the caller has them (a model with the same C, q, reg: a
    relinearisation's previous; ``TerminalCost.weights``).
    Checks (any fails: the output-weight fallback, its reason): the pencil's n eigenvalues
    inside the unit circle (those of Abar - Bbar K: a stabilising P), P finite, its relative
    residual <= DARE_RTOL (P is the subspace's answer), P positive definite (its Cholesky
    factor is T).
    """
    ab, c_bar = augmented(model)
    n_s = ab.shape[0]
    a_bar, b_bar = ab[:, :n_s], ab[:, n_s:]
    if weights is None:
        q_out = c_bar.T @ (q[:, None] * c_bar)
        eps = reg * max(np.linalg.norm(q_out, 2), 1e-12)
        weights = (q_out, q_out + eps * np.eye(n_s))
    q_out, q_bar = weights
    p, residual, reason, t_fac = None, float('nan'), '', None
    try:
        p = dare(a_bar, b_bar, q_bar, r)
    except (np.linalg.LinAlgError, ValueError) as err:
        reason = f'DARE failed: {err}'
    if p is not None:
        pp = float(np.vdot(p, p))
        if not math.isfinite(pp):
            reason = 'DARE solution not finite'
        else:
            # DARE(P) = A'P A_cl + Q - P, A_cl = A - BK, K = (R + B'PB)^{-1} B'PA
            pab = p @ ab                                  # [PA | PB]
            btp = b_bar.T @ pab                           # [B'PA | B'PB]
            btp[:, n_s:] += np.diag(r)
            gain = _solve(btp[:, n_s:], btp[:, :n_s])
            res = a_bar.T @ (pab[:, :n_s] - pab[:, n_s:] @ gain)
            res += q_bar
            res -= p
            residual = math.sqrt(float(np.vdot(res, res)) / max(pp, np.finfo(float).tiny))
            if not residual <= DARE_RTOL:
                reason = f'DARE residual {residual:.2e} > {DARE_RTOL:.0e}'
            else:
                chol, info = lapack.dpotrf(p, lower=0, clean=1)
                if info != 0:
                    reason = 'DARE solution not positive definite'
                t_fac = chol                              # upper: P = T'T
    s_r, s_e = _steady_state_map(model, q_out, c_bar, q)
    if reason:
        tracked = q > 0
        sq = np.sqrt(q[tracked])
        return TerminalCost(P=q_out, T=sq[:, None] * c_bar[tracked],
                            M=sq[:, None] * np.eye(len(q))[tracked], ss_r=s_r, ss_e=s_e,
                            dare_unusable=True, residual=residual, reason=reason,
                            weights=weights)
    return TerminalCost(P=p, T=t_fac, M=np.zeros((n_s, len(q))), ss_r=s_r, ss_e=s_e,
                        dare_unusable=False, residual=residual, reason='', weights=weights)


def _steady_state_map(model: LatentModel, q_out: np.ndarray, c_bar: np.ndarray,
                      q: np.ndarray) -> tuple:
    """(S_r (n_s, n_y), S_e (n_s, n_z)) with s_ss = S_r (r - d) + S_e e, the steady state that
    best matches the reference r under weights q (q_out = Cbar'QCbar): the KKT solution of
    argmin ||Q^{1/2} (Cbar s + d - r)||^2 s.t. (A - I) z + B u + e = 0."""
    n_z, n_y, n_s = model.n_z, len(q), c_bar.shape[1]
    parts = _constant_parts(n_z, n_s - n_z, n_y)
    kkt, rhs = parts[2].copy(), parts[3].copy()
    kkt[:n_s, :n_s] = q_out
    kkt[n_s:, :n_z] += model.A
    kkt[n_s:, n_z:n_s] = model.B
    kkt[:n_s, n_s:] = kkt[n_s:, :n_s].T
    np.multiply(c_bar.T, q, out=rhs[:n_s, :n_y])
    # The KKT solution by LU where the matrix is well conditioned (1-norm reciprocal condition
    # above KKT_RCOND); else the minimum-norm least-squares one (the pseudo-inverse's, with its
    # cut-off: numpy's lstsq, LAPACK's dgelsd): when the tracked outputs leave part of the
    # steady state free, any KKT solution is optimal; stabilisability (checked by the DARE)
    # makes the constraint rows full rank, so one exists.
    lu, piv, info = lapack.dgetrf(kkt)
    if info == 0 and lapack.dgecon(lu, lapack.dlange('1', kkt), norm='1')[0] > KKT_RCOND:
        sol = lapack.dgetrs(lu, piv, rhs, overwrite_b=1)[0]
    else:
        lwork, iwork = parts[4]
        sol = lapack.dgelsd(kkt, rhs, lwork, iwork, np.finfo(float).eps * kkt.shape[0],
                            overwrite_a=1, overwrite_b=1)[0]
    return sol[:n_s, :n_y], sol[:n_s, n_y:]
