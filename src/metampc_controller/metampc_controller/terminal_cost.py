"""Terminal cost of the latent MPC: the DARE weight P of eq. (mpc), made consistent.

The state is augmented with the previous input, s_k = [z_k; u_k] (n_s = n_z + n_u), so that du_k =
u_{k+1} - u_k is the input of a linear system (Abar = [[A, B], [0, I]], Bbar = [[B], [I]], Cbar =
[C, 0]); P is the stabilising solution of the paper's DARE posed for (Abar, Bbar, Qbar = Cbar' Q
Cbar + eps I, R) rather than eq. (compact)'s state, and the terminal cost (s_N - s_ss)' P (s_N -
s_ss) is centred on the steady state s_ss that best meets r_N (affine in r_N, from the KKT matrix).
When the DARE fails (exception, non-finite or non-definite P, residual above ``DARE_RTOL``,
unstable closed loop) it falls back to the stage output term (P = Cbar' Q Cbar) and says why. Both
are stored as least-squares rows (P = T'T). Given a nearby model's P (a planner relinearising every
tick), Newton's method (Hewer) from it solves the DARE instead of the QZ method. Derivation and
checks: docs/mpc.md#terminal-cost-a-consistent-dare.
"""
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.linalg

from metampc_model.latent_model import LatentModel

# A stabilising DARE solution of a well-posed problem meets ~1e-12; 1e-6 only rejects garbage.
DARE_RTOL = 1e-6
# Newton from a nearby solution converges quadratically: a few steps reach rounding, or the
# warm start is not near enough and the QZ method solves from scratch.
NEWTON_STEPS = 6
NEWTON_RTOL = 1e-12


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
    """

    P: np.ndarray
    T: np.ndarray
    M: np.ndarray
    ss_r: np.ndarray
    ss_e: np.ndarray
    dare_unusable: bool
    residual: float
    reason: str


def augmented(model: LatentModel) -> tuple:
    """(Abar (n_s, n_s), Bbar (n_s, n_u), ebar (n_s,), Cbar (n_y, n_s)) of the Delta-u system."""
    n_z, n_u = model.n_z, model.n_u
    a_bar = np.block([[model.A, model.B], [np.zeros((n_u, n_z)), np.eye(n_u)]])
    b_bar = np.vstack([model.B, np.eye(n_u)])
    e_bar = np.concatenate([model.e, np.zeros(n_u)])
    c_bar = np.hstack([model.C, np.zeros((model.n_y, n_u))])
    return a_bar, b_bar, e_bar, c_bar


def dare_residual(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray,
                  p: np.ndarray) -> float:
    """Relative residual ||A'PA - P - A'PB (R + B'PB)^{-1} B'PA + Q||_F / ||P||_F."""
    pb = p @ b
    res = a.T @ p @ a - p - a.T @ pb @ np.linalg.solve(r + b.T @ pb, pb.T @ a) + q
    return float(np.linalg.norm(res) / max(np.linalg.norm(p), np.finfo(float).tiny))


def dare_newton(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray,
                p0: np.ndarray) -> Optional[np.ndarray]:
    """The stabilising solution of the DARE by Newton's method (Hewer 1971) from p0 (n, n):
    K = (R + B'PB)^{-1} B'PA, then P solves the Stein equation P = (A - BK)' P (A - BK) + Q +
    K'RK, until P moves by <= NEWTON_RTOL relative. None where a gain is not stabilising (p0
    not near enough) or it has not converged in NEWTON_STEPS."""
    p = p0
    n = a.shape[0]
    eye = np.eye(n * n)
    for _ in range(NEWTON_STEPS):
        gain = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
        a_cl = a - b @ gain
        if max(abs(np.linalg.eigvals(a_cl))) >= 1.0:
            return None
        # vec(P) = (I - A_cl' (x) A_cl')^{-1} vec(Q + K'RK): n^2 unknowns, small n.
        rhs = q + gain.T @ r @ gain
        p_new = np.linalg.solve(eye - np.kron(a_cl.T, a_cl.T), rhs.reshape(-1)).reshape(n, n)
        p_new = 0.5 * (p_new + p_new.T)
        done = np.linalg.norm(p_new - p) <= NEWTON_RTOL * np.linalg.norm(p_new)
        p = p_new
        if done:
            return p if np.all(np.isfinite(p)) else None
    return None


def terminal_cost(model: LatentModel, q: np.ndarray, r: np.ndarray, reg: float,
                  warm: Optional[np.ndarray] = None) -> TerminalCost:
    """Terminal cost for output weights q (n_y,) >= 0, Delta-u weights r (n_u,) > 0.

    reg: relative eps of the state-weight regularisation Qbar = Cbar'QCbar + eps I.
    warm: a nearby model's DARE solution (n_s, n_s): Newton's method from it (dare_newton),
    the QZ method where that fails. The same checks follow either way.
    """
    a_bar, b_bar, _, c_bar = augmented(model)
    n_s = a_bar.shape[0]
    q_out = c_bar.T @ (q[:, None] * c_bar)
    eps = reg * max(np.linalg.norm(q_out, 2), 1e-12)
    q_bar = q_out + eps * np.eye(n_s)
    r_mat = np.diag(r)
    p, residual, reason = None, float('nan'), ''
    if warm is not None and warm.shape == (n_s, n_s):
        p = dare_newton(a_bar, b_bar, q_bar, r_mat, warm)
    try:
        if p is None:
            p = scipy.linalg.solve_discrete_are(a_bar, b_bar, q_bar, r_mat)
    except (np.linalg.LinAlgError, ValueError) as err:
        reason = f'DARE failed: {err}'
    if p is not None:
        p = 0.5 * (p + p.T)
        if not np.all(np.isfinite(p)):
            reason = 'DARE solution not finite'
        else:
            residual = dare_residual(a_bar, b_bar, q_bar, r_mat, p)
            gain = np.linalg.solve(r_mat + b_bar.T @ p @ b_bar, b_bar.T @ p @ a_bar)
            rho = max(abs(np.linalg.eigvals(a_bar - b_bar @ gain)))
            if residual > DARE_RTOL:
                reason = f'DARE residual {residual:.2e} > {DARE_RTOL:.0e}'
            elif rho >= 1.0:
                reason = f'DARE gain not stabilising (spectral radius {rho:.4f})'
            elif np.linalg.eigvalsh(p)[0] <= 0.0:
                reason = 'DARE solution not positive definite'
    s_r, s_e = _steady_state_map(model, q, c_bar)
    if reason:
        tracked = q > 0
        sq = np.sqrt(q[tracked])
        return TerminalCost(P=q_out, T=sq[:, None] * c_bar[tracked],
                            M=sq[:, None] * np.eye(len(q))[tracked], ss_r=s_r, ss_e=s_e,
                            dare_unusable=True, residual=residual, reason=reason)
    t_fac = np.linalg.cholesky(p).T
    return TerminalCost(P=p, T=t_fac, M=np.zeros((n_s, len(q))), ss_r=s_r, ss_e=s_e,
                        dare_unusable=False, residual=residual, reason='')


def _steady_state_map(model: LatentModel, q: np.ndarray, c_bar: np.ndarray) -> tuple:
    """(S_r (n_s, n_y), S_e (n_s, n_z)) with s_ss = S_r (r - d) + S_e e, the steady state that
    best matches the reference r under weights q: the KKT solution of
    argmin ||Q^{1/2} (Cbar s + d - r)||^2 s.t. (A - I) z + B u + e = 0."""
    n_z, n_s = model.n_z, c_bar.shape[1]
    eq = np.hstack([model.A - np.eye(n_z), model.B])
    kkt = np.block([[c_bar.T @ (q[:, None] * c_bar), eq.T], [eq, np.zeros((n_z, n_z))]])
    # pinv: when the tracked outputs leave part of the steady state free, any KKT solution is
    # optimal; stabilisability (checked by the DARE) makes eq full row rank, so one exists.
    kkt_inv = scipy.linalg.pinv(kkt)
    return kkt_inv[:n_s, :n_s] @ (c_bar.T * q), -kkt_inv[:n_s, n_s:]
