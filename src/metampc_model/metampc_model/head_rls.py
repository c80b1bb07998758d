"""Recursive least squares on a head that enters linearly, y = Theta phi, from a prior head.

Theta_t minimises J_t = lam J_{t-1} + (1 - lam) r0 |Theta - Theta_bar|^2 + |y_t - Theta phi_t|^2,
J_0 = r0 |Theta - Theta_bar|^2 (forgetting regularised toward the prior, Kulhavy 1987): in
information form R_t = lam R_{t-1} + (1 - lam) r0 I + phi phi', b_t = lam b_{t-1} +
(1 - lam) r0 Theta_bar' + phi y', Theta_t = (R_t^{-1} b_t)'. R_t >= r0 I (no wind-up), and a
direction the samples stop exciting relaxes to the prior. lam = 1 is the batch ridge of
:func:`metampc_learner.closed_form.ridge` on the same M samples with r0 = M gamma / 2. The
one-step predictive std of output i: sqrt(s2_i (1 + phi' R^{-1} phi)), s2_i the forgotten mean
of e_i^2 / (1 + phi' R^{-1} phi) (e the a-priori error). A non-finite sample leaves the estimate
unchanged; an R that is not positive definite is reset to the prior (both counted). Numpy only.
"""
from typing import Optional, Tuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve, LinAlgError, solve_triangular


class HeadRls:
    """The recursion of the module docstring on one head (n_y, n_phi), any units.

    Args:
        prior: Theta_bar (n_y, n_phi), the estimate's start and its anchor.
        precision: r0 > 0, the prior's precision per entry (sum-of-squares units).
        forgetting: lam in (0, 1]; 1 keeps every sample (the batch ridge).
    """

    def __init__(self, prior: np.ndarray, precision: float, forgetting: float = 1.0):
        if not (precision > 0 and 0 < forgetting <= 1):
            raise ValueError(f'need precision > 0 and forgetting in (0, 1], got {precision}, '
                             f'{forgetting}')
        self.prior = np.array(prior, dtype=np.float64)
        if self.prior.ndim != 2 or not np.all(np.isfinite(self.prior)):
            raise ValueError(f'the prior head must be a finite (n_y, n_phi) array, got shape '
                             f'{self.prior.shape}')
        self.precision = float(precision)
        self.forgetting = float(forgetting)
        self.updates = 0          # samples taken
        self.skipped = 0          # non-finite samples left out
        self.resets = 0           # R lost positive definiteness: back to the prior
        self.reset()

    def reset(self) -> None:
        """Back to the prior: Theta = Theta_bar, R = r0 I, no noise estimate."""
        n_y, n = self.prior.shape
        self.head = self.prior.copy()
        self.info = self.precision * np.eye(n)
        self.rhs = self.precision * self.prior.T.copy()      # b = R Theta' (n_phi, n_y)
        self._chol = (np.sqrt(self.precision) * np.eye(n), True)
        self.noise = np.full(n_y, np.nan)                     # s2 per output
        self._weight = 0.0
        self.since_prior = 0      # samples taken since this reset

    def leverage(self, phi: np.ndarray) -> float:
        """phi' R^{-1} phi of the current estimate."""
        c, lower = self._chol
        v = solve_triangular(c, phi, trans='T' if not lower else 'N', lower=lower)
        return float(v @ v)

    def predictive_std(self, phi: np.ndarray) -> np.ndarray:
        """(n_y,) std of the one-step prediction Theta phi: sqrt(s2 (1 + phi' R^{-1} phi))
        (NaN until a sample has been taken)."""
        return np.sqrt(self.noise * (1.0 + self.leverage(np.asarray(phi, np.float64))))

    def candidate(self, phi: np.ndarray, y: np.ndarray
                  ) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, tuple]]:
        """(head, R, b, Cholesky factor of R) after the sample (phi (n_phi,), y (n_y,)),
        without taking it; None if R lost positive definiteness (:meth:`take` resets)."""
        lam, r0 = self.forgetting, self.precision
        info = lam * self.info + np.outer(phi, phi)
        rhs = lam * self.rhs + np.outer(phi, y)
        if lam < 1.0:
            info[np.diag_indices_from(info)] += (1.0 - lam) * r0
            rhs += (1.0 - lam) * r0 * self.prior.T
        try:
            chol = cho_factor(info, lower=True, check_finite=True)
        except (LinAlgError, ValueError):
            return None
        return cho_solve(chol, rhs).T, info, rhs, chol

    def take(self, phi: np.ndarray, y: np.ndarray, candidate=None) -> str:
        """Update by the sample (phi (n_phi,), y (n_y,)); `candidate` the one
        :meth:`candidate` made of it (None: made here). Returns 'taken', 'skipped' (a
        non-finite sample: nothing changes) or 'reset' (R lost positive definiteness: the
        prior again)."""
        phi, y = np.asarray(phi, np.float64), np.asarray(y, np.float64)
        if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(y))):
            self.skipped += 1
            return 'skipped'
        error = y - self.head @ phi
        scaled = error ** 2 / (1.0 + self.leverage(phi))
        candidate = candidate if candidate is not None else self.candidate(phi, y)
        if candidate is None or not np.all(np.isfinite(candidate[0])):
            self.resets += 1
            self.reset()
            return 'reset'
        self.head, self.info, self.rhs, self._chol = candidate
        self._weight = self.forgetting * self._weight + 1.0
        noise = np.where(np.isfinite(self.noise), self.noise, 0.0)
        self.noise = noise + (scaled - noise) / self._weight
        self.updates += 1
        self.since_prior += 1
        return 'taken'


__all__ = ['HeadRls']
