"""The batched meta-gradients of iMAML-GN and first-order MAML, written on (B, ...) tensors.

The fast backend of meta-training (``MetaConfig.backend = 'fast'``): for the B tasks of an
outer step at once it computes what ``vmap(ImamlTaskGradient)`` (Gauss-Newton curvature) and
``vmap(FirstOrderMamlTaskGradient)`` compute (the reference: imaml.py, maml.py, equal to
float32 rounding, test_batched_objective.py): the NSSM of eq. (SSM) for (B, P) weight vectors,
the inner loop of eq. (inner_imaml) / eq. (inner), the Gauss-Newton products of eq. (Qb), CG of
eq. (cg), P_b of eq. (meta_gradient) and the anchor of eq. (outer), with gradients written out
by hand (no autograd graph) into preallocated (B, P) buffers. Runs on ``device`` ('cpu' or
'cuda'); the TaskGradient comes back on it. Deterministic on the CPU for a fixed thread count
(dense products, element-wise ops and sums only). How and why: docs/learning.md, Speed of the
meta-gradient.
"""
from dataclasses import dataclass
from typing import Callable, List, NamedTuple, Tuple

import torch

from metampc_model.latent_stability import SMALL
from metampc_model.nssm import Nssm
from metampc_learner.task_gradient import TaskGradient
from metampc_learner.training_vector import TrainingVector

_relu_backward = torch.ops.aten.threshold_backward


class Batch(NamedTuple):
    """B data sets of N windows, cut for the batched model (see BatchedNssm.windows).

    Attributes:
        x: encoder inputs (B, N, H (n_u + n_y)), pairs (u_k, y_k) oldest first.
        u_future: u_{t+1..t+T} (B, N, T n_u).
        target: y_{t+1..t+T} (B, N, T n_y).
        n_terms: N T, the loss's divisor.
    """

    x: torch.Tensor
    u_future: torch.Tensor
    target: torch.Tensor
    n_terms: int


class Head(NamedTuple):
    """The linear part of eqs. (z_next), (haty) for B tasks and what its derivatives need.

    Attributes:
        f: stacked C A^k, k = 1..T (B, T n_y, n_z).
        k: block Toeplitz C A^(k-j) B where j <= k, else 0 (B, T n_y, T n_u).
        powers: C A^k, k = 0..T (B, T+1, n_y, n_z).
        a, b, w: A, B and the trained coordinates W of A (W = A without stable_latent).
        phi, dphi: A = W phi(x), x = ||W||_2 / rho_max, and phi'(x) (B, 1, 1).
        u1, v1: leading singular vectors of W (B, n_z, 1), (B, 1, n_z).
    """

    f: torch.Tensor
    k: torch.Tensor
    powers: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    w: torch.Tensor
    phi: torch.Tensor
    dphi: torch.Tensor
    u1: torch.Tensor
    v1: torch.Tensor


class Forward(NamedTuple):
    """One batched forward pass and what its derivatives need.

    Attributes:
        pred: y_hat (B, N, T n_y).
        weights: the split flat vector, one (B, ...) view per parameter (A's slot holds W).
        hidden: the encoder's post-ReLU activations, layer by layer (B, N, width).
        z: z_t (B, N, n_z).
        head: the linear part (:class:`Head`).
    """

    pred: torch.Tensor
    weights: List[torch.Tensor]
    hidden: List[torch.Tensor]
    z: torch.Tensor
    head: Head


class BatchedNssm:
    """The NSSM of eq. (SSM) evaluated for B flat weight vectors (B, P) at once, with its
    reverse-mode (:meth:`pullback`) and forward-mode (:meth:`push`) derivatives."""

    def __init__(self, model: Nssm, device='cpu'):
        cfg = model.config
        self.config = cfg
        self.device = torch.device(device)
        self.dtype = next(model.parameters()).dtype
        self.spec = TrainingVector(cfg)
        self.shapes = list(self.spec.shapes.values())
        self.n_layers = len(cfg.hidden) + 1
        t = cfg.loss_horizon
        lag = torch.arange(t)[:, None] - torch.arange(t)[None, :]
        # shift[l, k, j] = 1 where k - j = l: K = sum_l shift_l (x) C A^l B is a product,
        # and so is its adjoint (no index_put accumulation: deterministic on a GPU too)
        self.shift = (lag[None] == torch.arange(t)[:, None, None]).to(self.device, self.dtype)

    @property
    def size(self) -> int:
        """P, the number of weights."""
        return self.spec.size

    def windows(self, u: torch.Tensor, y: torch.Tensor) -> Batch:
        """Windows u (B, N, H+T, n_u), y (B, N, H+T, n_y) -> a Batch on the device."""
        u = u.to(self.device, self.dtype)
        y = y.to(self.device, self.dtype)
        h = self.config.history
        x = torch.cat([u[:, :, :h], y[:, :, :h]], dim=-1).flatten(start_dim=-2)
        return Batch(x, u[:, :, h:].flatten(start_dim=-2), y[:, :, h:].flatten(start_dim=-2),
                     u.shape[1] * self.config.loss_horizon)

    def split(self, flat: torch.Tensor) -> List[torch.Tensor]:
        """(B, P) -> one (B, *shape) view per parameter, canonical order (no copy)."""
        chunks = torch.split(flat, self.spec.sizes, dim=-1)
        return [c.view(c.shape[0], *s) for c, s in zip(chunks, self.shapes)]

    def head(self, w: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> Head:
        """Eqs. (z_next), (haty) as matrices: y_hat = z F' + u_future K'.

        y_hat_{t+k} = C A^k z_t + sum_{j=1..k} C A^(k-j) B u_{t+j}, Nssm.rollout's closed form;
        A = latent_stability.bounded_transition(W) with stable_latent.
        """
        cfg = self.config
        if cfg.stable_latent:
            finite = torch.nan_to_num(w, nan=0.0, posinf=0.0, neginf=0.0)
            u, s, vh = torch.linalg.svd(finite)
            x = s[:, :1, None] / cfg.rho_max
            small = x < SMALL
            safe = torch.where(small, torch.ones_like(x), x)
            tanh = torch.tanh(safe)
            phi = torch.where(small, 1 - x.square() / 3, tanh / safe)
            dphi = torch.where(small, -2 * x / 3, (1 - tanh.square()) / safe - tanh / safe ** 2)
            a = w * phi
            u1, v1 = u[:, :, :1], vh[:, :1, :]
        else:
            a, phi = w, torch.ones_like(w[:, :1, :1])
            dphi, u1, v1 = torch.zeros_like(phi), w[:, :, :1], w[:, :1, :]
        powers = [c]
        for _ in range(cfg.loss_horizon):
            powers.append(torch.bmm(powers[-1], a))
        powers = torch.stack(powers, dim=1)
        f, k = self._matrices(powers, b)
        return Head(f, k, powers, a, b, w, phi, dphi, u1, v1)

    def _matrices(self, powers: torch.Tensor, b: torch.Tensor
                  ) -> Tuple[torch.Tensor, torch.Tensor]:
        """(C A^k for k = 0..T, B) -> (F, K); linear in each argument."""
        cfg = self.config
        n_b = powers.shape[0]
        markov = torch.matmul(powers[:, :-1], b[:, None])               # (B, T, n_y, n_u)
        k = torch.einsum('lkj,blyu->bkyju', self.shift, markov)
        return (powers[:, 1:].reshape(n_b, -1, cfg.n_z),
                k.reshape(n_b, cfg.loss_horizon * cfg.n_y, cfg.loss_horizon * cfg.n_u))

    def _head_tangent(self, hd: Head, dw: torch.Tensor, db: torch.Tensor, dc: torch.Tensor
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
        """(dF, dK) for the tangent (dW, dB, dC): forward mode through :meth:`head`."""
        cfg = self.config
        d_a = dw * hd.phi
        if cfg.stable_latent:    # dA = dW phi + W phi'(x) dx,  dx = u1' dW v1 / rho_max
            dx = torch.bmm(torch.bmm(hd.u1.transpose(1, 2), dw), hd.v1.transpose(1, 2))
            d_a = d_a + hd.w * (hd.dphi * dx / cfg.rho_max)
        d_powers = [dc]
        for j in range(cfg.loss_horizon):
            d_powers.append(torch.baddbmm(torch.bmm(hd.powers[:, j], d_a), d_powers[-1], hd.a))
        d_powers = torch.stack(d_powers, dim=1)
        d_f, d_k = self._matrices(d_powers, hd.b)
        _, d_k_b = self._matrices(hd.powers, db)
        return d_f, d_k + d_k_b

    def _head_adjoint(self, hd: Head, d_f: torch.Tensor, d_k: torch.Tensor
                      ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(dL/dW, dL/dB, dL/dC) from (dL/dF, dL/dK): reverse mode through :meth:`head`."""
        cfg = self.config
        n_b, t = d_f.shape[0], cfg.loss_horizon
        d_markov = torch.einsum('lkj,bkyju->blyu', self.shift,
                                d_k.view(n_b, t, cfg.n_y, t, cfg.n_u))  # (B, T, n_y, n_u)
        before = hd.powers[:, :-1]                                       # C A^k, k = 0..T-1
        d_b = torch.matmul(before.transpose(-1, -2), d_markov).sum(dim=1)
        direct = torch.matmul(d_markov, hd.b[:, None].transpose(-1, -2))  # dL/d(C A^k), k < T
        d_f = d_f.view(n_b, t, cfg.n_y, cfg.n_z)
        adj = [d_f[:, t - 1]]                                              # total, k = T..0
        a_t = hd.a.transpose(1, 2)
        for j in range(t - 1, -1, -1):
            own = direct[:, j] + (d_f[:, j - 1] if j > 0 else 0)
            adj.append(torch.baddbmm(own, adj[-1], a_t))
        adj = torch.stack(adj[::-1], dim=1)                                # k = 0..T
        d_a = torch.matmul(before.transpose(-1, -2), adj[:, 1:]).sum(dim=1)
        d_w = d_a * hd.phi
        if cfg.stable_latent:    # + <dA, W> phi'(x) / rho_max * u1 v1'
            inner = (d_a * hd.w).sum(dim=(1, 2), keepdim=True)
            d_w = d_w + (inner * hd.dphi / cfg.rho_max) * torch.bmm(hd.u1, hd.v1)
        return d_w, d_b, adj[:, 0]

    def forward(self, flat: torch.Tensor, data: Batch) -> Forward:
        """y_hat for every task, with what :meth:`pullback` and :meth:`push` need."""
        weights = self.split(flat)
        hidden = []
        h = data.x
        for i in range(self.n_layers):
            w, b = weights[2 * i], weights[2 * i + 1]
            h = torch.baddbmm(b[:, None, :], h, w.transpose(1, 2))
            if i < self.n_layers - 1:
                h = h.relu_()
                hidden.append(h)
        hd = self.head(*weights[-3:])
        pred = torch.baddbmm(torch.bmm(h, hd.f.transpose(1, 2)), data.u_future,
                             hd.k.transpose(1, 2))
        return Forward(pred, weights, hidden, h, hd)

    def pullback(self, fwd: Forward, data: Batch, w: torch.Tensor, out: torch.Tensor
                 ) -> torch.Tensor:
        """J' w for every task into `out` (B, P): w (B, N, T n_y), J = d y_hat / d flat."""
        views = self.split(out)
        w_t = w.transpose(1, 2)
        d_h = torch.bmm(w, fwd.head.f)                                   # dL/dz
        for i in reversed(range(self.n_layers)):
            if i < self.n_layers - 1:
                d_h = _relu_backward(d_h, fwd.hidden[i], 0)
            inp = fwd.hidden[i - 1] if i > 0 else data.x
            torch.bmm(d_h.transpose(1, 2), inp, out=views[2 * i])
            torch.sum(d_h, dim=1, out=views[2 * i + 1])
            if i > 0:
                d_h = torch.bmm(d_h, fwd.weights[2 * i])
        head = self._head_adjoint(fwd.head, torch.bmm(w_t, fwd.z),
                                  torch.bmm(w_t, data.u_future))
        for view, g in zip(views[-3:], head):
            view.copy_(g)
        return out

    def push(self, fwd: Forward, data: Batch, v: torch.Tensor) -> torch.Tensor:
        """J v for every task: v (B, P) -> (B, N, T n_y) (forward mode, from the activations)."""
        tangents = self.split(v)
        d_h = None
        for i in range(self.n_layers):
            w, dw, db = fwd.weights[2 * i], tangents[2 * i], tangents[2 * i + 1]
            inp = fwd.hidden[i - 1] if i > 0 else data.x
            d_a = torch.baddbmm(db[:, None, :], inp, dw.transpose(1, 2))
            if d_h is not None:
                d_a = torch.baddbmm(d_a, d_h, w.transpose(1, 2))
            d_h = _relu_backward(d_a, fwd.hidden[i], 0) if i < self.n_layers - 1 else d_a
        d_f, d_k = self._head_tangent(fwd.head, *tangents[-3:])
        out = torch.baddbmm(torch.bmm(d_h, fwd.head.f.transpose(1, 2)), fwd.z,
                            d_f.transpose(1, 2))
        return torch.baddbmm(out, data.u_future, d_k.transpose(1, 2))

    def loss(self, fwd: Forward, data: Batch) -> Tuple[torch.Tensor, torch.Tensor]:
        """(l_SSM per task (B,), the residual y_hat - y (B, N, T n_y))."""
        residual = fwd.pred - data.target
        return residual.square().sum(dim=(1, 2)) / data.n_terms, residual

    def loss_and_grad(self, flat: torch.Tensor, data: Batch, out: torch.Tensor
                      ) -> torch.Tensor:
        """l_SSM(D_b; flat_b) per task (B,); its gradient goes into `out` (B, P)."""
        fwd = self.forward(flat, data)
        loss, residual = self.loss(fwd, data)
        self.pullback(fwd, data, residual * (2.0 / data.n_terms), out)
        return loss

    def gauss_newton(self, flat: torch.Tensor, data: Batch
                     ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """(v, out) -> out = G_b v_b, G = (2 / (N T)) J'J at flat (curvature.py), per task."""
        fwd = self.forward(flat, data)
        scale = 2.0 / data.n_terms
        return lambda v, out: self.pullback(fwd, data, self.push(fwd, data, v) * scale, out)


def inner_loop(net: BatchedNssm, omega: torch.Tensor, data: Batch, steps: int, lr: float,
               gamma: float) -> torch.Tensor:
    """Eq. (inner_imaml) (gamma > 0) or eq. (inner) (gamma = 0) for every task: (B, P).

    FlatObjective.prox_step's safeguard with one objective evaluation per step: the step
    psi - rate g is taken unless it raises l_SSM(D_tr; .) + gamma/2 ||. - omega||^2 by more
    than rounding (relative sqrt(eps)) or makes it non-finite; a refused step keeps psi (and
    so its gradient) and halves that task's rate.
    """
    if steps == 0:
        return omega.clone()
    psi, g = omega.clone(), torch.empty_like(omega)
    value = net.loss_and_grad(psi, data, g)                        # at omega: no prox term
    candidate, g_new = torch.empty_like(omega), torch.empty_like(omega)
    diff = torch.empty_like(omega) if gamma else None
    rate = torch.full_like(value, lr)
    root_eps = torch.finfo(value.dtype).eps ** 0.5
    for step in range(steps):
        last = step == steps - 1
        torch.addcmul(psi, rate[:, None], g, value=-1, out=candidate)
        fwd = net.forward(candidate, data)
        trial, residual = net.loss(fwd, data)
        if gamma:
            torch.sub(candidate, omega, out=diff)
            trial = trial + 0.5 * gamma * torch.linalg.vecdot(diff, diff)
        ok = trial <= value + root_eps * value.abs()                # NaN fails it too
        if not last:
            net.pullback(fwd, data, residual * (2.0 / data.n_terms), g_new)
            if gamma:
                g_new.add_(diff, alpha=gamma)
        if bool(ok.all()):        # the usual case: swap the buffers, no copy
            psi, candidate = candidate, psi
            g, g_new = g_new, g
            value = trial
        else:
            torch.where(ok[:, None], candidate, psi, out=psi)
            if not last:
                torch.where(ok[:, None], g_new, g, out=g)
            value = torch.where(ok, trial, value)
        rate = torch.where(ok, rate, 0.5 * rate)
    return psi


def conjugate_gradient(matvec: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                       b: torch.Tensor, steps: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Eq. (cg) for the B systems Q_b x_b = b_b at once, cg.conjugate_gradient row by row.

    Args:
        matvec: (p, out) -> out = Q p, row by row (B, P).
        b: right-hand sides (B, P).
        steps: CG iterations from x = 0.

    Returns:
        x (B, P) and the relative recursive residuals (B,).
    """
    tiny = torch.finfo(b.dtype).tiny

    def ratio(num, den):
        ok = den.abs() > tiny
        return torch.where(ok, num / torch.where(ok, den, 1.0), 0.0)

    def dot(p, q):
        return torch.linalg.vecdot(p, q)[:, None]

    x, r, p, qp = torch.zeros_like(b), b.clone(), b.clone(), torch.empty_like(b)
    rr = dot(r, r)
    for _ in range(steps):
        matvec(p, qp)
        alpha = ratio(rr, dot(p, qp))
        x.addcmul_(alpha, p)
        r.addcmul_(alpha, qp, value=-1)
        rr_new = dot(r, r)
        torch.addcmul(r, ratio(rr_new, rr), p, out=p)
        rr = rr_new
    return x, torch.sqrt(ratio(rr, dot(b, b))).squeeze(-1)


@dataclass
class BatchedTaskGradient:
    """(omega (P,), tr_u, tr_y, te_u, te_y with a leading B) -> TaskGradient batched over B.

    The fast equivalent of ``vmap(meta_train.task_gradient_fn(...))`` for method 'imaml'
    (Gauss-Newton curvature) or 'maml' (first-order), anchored when init_loss_weight > 0.
    The result lies on the net's device.

    Attributes:
        net: the batched NSSM (its device is where everything runs).
        method: 'imaml' or 'maml'.
        inner_steps, lr_inner, gamma, cg_steps, init_loss_weight: as in MetaConfig.
    """

    net: BatchedNssm
    method: str
    inner_steps: int
    lr_inner: float
    gamma: float
    cg_steps: int
    init_loss_weight: float = 0.0

    def __post_init__(self):
        if self.method not in ('imaml', 'maml'):
            raise ValueError(f"the fast backend computes 'imaml' and 'maml', not "
                             f'{self.method!r}')

    def __call__(self, omega: torch.Tensor, tr_u: torch.Tensor, tr_y: torch.Tensor,
                 te_u: torch.Tensor, te_y: torch.Tensor) -> TaskGradient:
        with torch.no_grad():
            return self._compute(omega, tr_u, tr_y, te_u, te_y)

    def _compute(self, omega, tr_u, tr_y, te_u, te_y) -> TaskGradient:
        net = self.net
        train, test = net.windows(tr_u, tr_y), net.windows(te_u, te_y)
        omega_b = omega.detach().to(net.device, net.dtype).expand(tr_u.shape[0], -1)
        omega_b = omega_b.contiguous()
        imaml = self.method == 'imaml'
        psi = inner_loop(net, omega_b, train, self.inner_steps, self.lr_inner,
                         self.gamma if imaml else 0.0)
        p_b = torch.empty_like(psi)
        test_loss = net.loss_and_grad(psi, test, p_b)                 # eq. (meta_gradient)
        if imaml:                                                      # eqs. (Qb), (cg)
            curv = net.gauss_newton(psi, train)

            def matvec(v, out):
                return torch.add(v, curv(v, out), alpha=1.0 / self.gamma, out=out)

            meta_grad, residual = conjugate_gradient(matvec, p_b, self.cg_steps)
        else:                                                          # eq. (appro)
            meta_grad, residual = p_b, torch.full_like(test_loss, float('nan'))
        if self.init_loss_weight > 0:                                  # the anchor
            anchor = torch.empty_like(psi)
            net.loss_and_grad(omega_b, test, anchor)
            meta_grad.add_(anchor, alpha=self.init_loss_weight)
        return TaskGradient(meta_grad, test_loss, residual, psi)


__all__ = ['Batch', 'BatchedNssm', 'BatchedTaskGradient', 'conjugate_gradient', 'Forward',
           'Head', 'inner_loop']
