"""The feature NARX as the controller runs it at every tick: numpy, physical units.

The numpy side of :mod:`metampc_model.feature_narx` (whose torch side trains it), as
:mod:`metampc_model.predictor` is the NSSM's: :meth:`NarxPredictor.encode` builds the regressor
state s_t from the latest samples (where the NSSM's encoder gives z_t), :meth:`~NarxPredictor.step`
is one step, :meth:`~NarxPredictor.linearise` the affine model exact to first order at
(s_t, u_{t+1}) that :class:`metampc_controller.local_mpc.LocalLinearMpc` plans on each tick (g's
Jacobian by the chain rule through its tanh layers), :meth:`~NarxPredictor.predict` the T-step
prediction. No torch.
"""
from typing import Any, Mapping, Optional, Tuple

import numpy as np

from metampc_model.arrays import as_numpy
from metampc_model.latent_model import LatentModel
from metampc_model.narx_shape import NarxShape
from metampc_model.normalisation import Normalisation


class NarxPredictor:
    """Numpy feature NARX: regressor state, one step, linearisation, prediction.

    Args:
        shape, norm: as the model's.
        params: g's parameters and 'head' (numpy arrays or torch tensors, any float dtype);
            copied to float64.
    """

    def __init__(self, shape: NarxShape, norm: Normalisation, params: Mapping[str, Any]):
        self.shape = shape
        self.norm = norm
        n_layers = len(shape.hidden) + 1 if shape.features else 0
        self._layers = [(np.array(as_numpy(params[f'g.{i}.weight'], np.float64)),
                         np.array(as_numpy(params[f'g.{i}.bias'], np.float64)))
                        for i in range(n_layers)]
        self._head = np.array(as_numpy(params['head'], np.float64))
        p = shape.order
        self._mean = np.concatenate([norm.y_mean] * p + [norm.u_mean] * (p - 1))
        self._std = np.concatenate([norm.y_std] * p + [norm.u_std] * (p - 1))
        # linearise's constant parts: dF/ds and dF/du from normalised to physical units, the
        # companion matrix's shifts, C and d (shared, read-only).
        n_s, n_y, n_u = shape.n_s, shape.n_y, shape.n_u
        self._scale_s = np.asarray(norm.y_std)[:, None] / self._std[None, :]
        self._scale_u = np.asarray(norm.y_std)[:, None] / np.asarray(norm.u_std)[None, :]
        a, b = np.zeros((n_s, n_s)), np.zeros((n_s, n_u))
        a[n_y:p * n_y, :(p - 1) * n_y] = np.eye((p - 1) * n_y)     # y lags shift
        if p > 1:
            b[p * n_y:p * n_y + n_u] = np.eye(n_u)                 # u_{t+1} becomes a lag
            a[p * n_y + n_u:, p * n_y:n_s - n_u] = np.eye((p - 2) * n_u)
        c = np.zeros((n_y, n_s))
        c[:, :n_y] = np.eye(n_y)
        self._shifts = (a, b, c, np.zeros(n_y))
        for part in self._shifts:
            part.flags.writeable = False

    @property
    def history(self) -> int:
        """Samples :meth:`encode` reads: the order p."""
        return self.shape.order

    def encode(self, u_hist: np.ndarray, y_hist: np.ndarray) -> np.ndarray:
        """Physical s_t (n_s,) from the latest samples, oldest first (at least p rows; row k of
        u_hist produced row k of y_hist, u_hist[-1] = u_t)."""
        p = self.shape.order
        ys = [y_hist[-1 - i] for i in range(p)]
        us = [u_hist[-1 - j] for j in range(p - 1)]
        return np.concatenate(ys + us).astype(np.float64)

    def _normalised(self, s: np.ndarray, u_next: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        nm = self.norm
        return ((np.asarray(s, np.float64) - self._mean) / self._std,
                (np.asarray(u_next, np.float64) - nm.u_mean) / nm.u_std)

    def _features(self, s_n: np.ndarray, jacobian: bool) -> Tuple[np.ndarray, list]:
        """(g(s_n) (F,), each layer's tanh slope 1 - h^2 (its width,), with `jacobian`)."""
        h, slopes = s_n, []
        for w, b in self._layers:
            h = np.tanh(w @ h + b)
            if jacobian:
                slopes.append(1.0 - h * h)
        return h if self._layers else np.zeros(0), slopes

    @property
    def head(self) -> np.ndarray:
        """Theta (n_y, n_phi), normalised units (read-only view)."""
        view = self._head.view()
        view.flags.writeable = False
        return view

    def set_head(self, head: np.ndarray) -> None:
        """Fly `head` (n_y, n_phi) from now on (the in-loop RLS: metampc_controller.narx_rls)."""
        head = np.array(head, dtype=np.float64)
        if head.shape != self._head.shape:
            raise ValueError(f'head of shape {head.shape}, the model has {self._head.shape}')
        self._head = head

    def _one_step(self, s_n: np.ndarray, u_n: np.ndarray, jacobian: bool = False,
                  head: Optional[np.ndarray] = None):
        """Normalised y_{t+1}, and with `jacobian` (dy/ds_n, dy/du_n) too (of `head`, default
        the model's): dy/ds_n = head_s + head_g dg/ds_n, the chain rule taken from the left
        (n_y rows through each layer's slope and weight)."""
        sh, head = self.shape, self._head if head is None else head
        g, slopes = self._features(s_n, jacobian)
        y_n = head @ np.concatenate([s_n, g, u_n, [1.0]])
        if not jacobian:
            return y_n
        n_s, n_f = sh.n_s, sh.features
        d_s = head[:, :n_s]
        if n_f:
            rows = head[:, n_s:n_s + n_f]
            for (w, _), slope in zip(reversed(self._layers), reversed(slopes)):
                rows = (rows * slope) @ w
            d_s = d_s + rows
        return y_n, d_s, head[:, n_s + n_f:n_s + n_f + sh.n_u]

    def regressors(self, s: np.ndarray, u_next: np.ndarray) -> np.ndarray:
        """phi(s_t, u_{t+1}) (n_phi,) = [s_n; g(s_n); u_n; 1], normalised, from physical s_t
        and u_{t+1}: y_{t+1} = y_std * (head @ phi) + y_mean."""
        s_n, u_n = self._normalised(s, u_next)
        return np.concatenate([s_n, self._features(s_n, False)[0], u_n, [1.0]])

    def step(self, s: np.ndarray, u_next: np.ndarray) -> np.ndarray:
        """y_{t+1} (n_y,) physical from s_t (n_s,) and u_{t+1} (n_u,) physical."""
        nm = self.norm
        return self._one_step(*self._normalised(s, u_next)) * nm.y_std + nm.y_mean

    def shift(self, s: np.ndarray, y_next: np.ndarray, u_next: np.ndarray) -> np.ndarray:
        """s_{t+1} from s_t, y_{t+1} and u_{t+1} (physical)."""
        p, n_y, n_u = self.shape.order, self.shape.n_y, self.shape.n_u
        ys = np.concatenate([y_next, s[:(p - 1) * n_y]])
        if p == 1:
            return ys
        return np.concatenate([ys, u_next, s[p * n_y:p * n_y + (p - 2) * n_u]])

    def predict(self, s: np.ndarray, u_future: np.ndarray) -> np.ndarray:
        """Physical y_{t+1..t+K} (K, n_y) from s_t and u_{t+1..t+K} (K, n_u), each prediction
        fed back into the lags."""
        u_future = np.asarray(u_future, np.float64).reshape(-1, self.shape.n_u)
        out = np.empty((u_future.shape[0], self.shape.n_y))
        for k, u in enumerate(u_future):
            out[k] = self.step(s, u)
            s = self.shift(s, out[k], u)
        return out

    def linearise(self, s: np.ndarray, u_next: np.ndarray, head: Optional[np.ndarray] = None
                  ) -> LatentModel:
        """The affine model of s_{t+1} = F(s_t, u_{t+1}) at (s, u_next), physical units:
        z = s, z+ = A z + B u + e exact to first order there (A the companion matrix whose
        first n_y rows are dF/ds), y = C z (C selects y_t), d = 0; of `head` in place of the
        model's where given. ValueError if the Jacobian is not finite."""
        nm, n_y = self.norm, self.shape.n_y
        s, u_next = np.asarray(s, np.float64), np.asarray(u_next, np.float64)
        y_n, d_s, d_u = self._one_step(*self._normalised(s, u_next), jacobian=True, head=head)
        top_s, top_u = d_s * self._scale_s, d_u * self._scale_u
        y_next = y_n * nm.y_std + nm.y_mean
        if not (np.isfinite(top_s).all() and np.isfinite(top_u).all()
                and np.isfinite(y_next).all()):
            raise ValueError('the feature NARX has a non-finite Jacobian here')
        a, b, c, d = self._shifts
        A, B, e = a.copy(), b.copy(), np.zeros(a.shape[0])
        A[:n_y], B[:n_y] = top_s, top_u
        e[:n_y] = y_next - top_s @ s - top_u @ u_next
        return LatentModel(A, B, c, e, d)


__all__ = ['NarxPredictor']
