"""Meta-inference (Algorithm 2, eq. infer) and the supervised baseline.

Adaptation: ``steps`` full-batch gradient steps on
``l_SSM(D_target; psi) + gamma/2 ||psi - omega_inf||^2`` from psi = omega_inf (gamma = 0: the
paper's plain steps of sec. Simulation). Supervised baseline: the same steps from a random
initialisation (gamma = 0). Both report the loss on held-out target windows before and after
every step.

Step rule (``rule``, every method): 'gradient' backtracks each step from the rate ``lr``
(Armijo, ``FlatObjective.armijo_step``: a rate too large for the target's curvature is halved
within the step, the next step tries ``lr`` again); 'gauss_newton' takes Levenberg-Marquardt
steps on the same objective (:mod:`.gauss_newton`, ``cg_steps`` of CG each; ``lr`` unused).
"""
import math
import time
from dataclasses import dataclass, field, replace
from typing import List, Optional

import torch

from metampc_common.params import check_fields, param
from metampc_model.nssm import init_params, Nssm, Params
from metampc_learner.data import Windows
from metampc_learner.gauss_newton import lm_step, MU_START
from metampc_learner.objective import FlatObjective
from metampc_learner.progress import Progress, ProgressFn


GRADIENT, GAUSS_NEWTON = 'gradient', 'gauss_newton'
RULES = (GRADIENT, GAUSS_NEWTON)


@dataclass
class AdaptConfig:
    """Attributes: steps (m), lr (beta_in), gamma (>= 0) of eq. (infer); the step rule and its
    CG iterations (module docstring)."""

    steps: int = param(20, 'adaptation gradient steps', ge=0, live=True)
    lr: float = param(0.05, 'adaptation step size', gt=0, live=True)
    gamma: float = param(0.0, 'proximal strength of eq. infer (0: plain gradient steps)', ge=0,
                         live=True)
    rule: str = param(GRADIENT, 'adaptation step rule: gradient (backtracked from lr) or '
                                'gauss_newton (Levenberg-Marquardt, lr unused)',
                      choices=RULES)
    cg_steps: int = param(30, 'CG iterations per gauss_newton step', ge=1)

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)


@dataclass
class AdaptResult:
    """Adapted weights omega* and loss curves (normalised units), each of length steps + 1.

    Attributes:
        params: omega*.
        train_loss: l_SSM(D_target; psi) before each step and after the last.
        heldout_loss: l_SSM on the held-out target windows, same indexing.
        rates: the step size each step took (gauss_newton: 1 / (gamma + damping)), 0.0 when no
            decrease was found and psi kept; length steps.
        elapsed: wall time, s.
    """

    params: Params
    train_loss: List[float] = field(default_factory=list)
    heldout_loss: List[float] = field(default_factory=list)
    rates: List[float] = field(default_factory=list)
    elapsed: float = 0.0


def adapt(model: Nssm, init: Params, train: Windows, heldout: Windows, config: AdaptConfig,
          progress: Optional[ProgressFn] = None, anchor: Optional[Params] = None
          ) -> AdaptResult:
    """Eq. (infer) from `init` (omega_inf) on the target windows `train`.

    `anchor`: the proximal term's centre when it is not `init` (adaptation in the loop starts
    from the model in use and stays anchored to the meta-model).

    Raises:
        ValueError: no training windows, or a loss turned non-finite.
    """
    config.validate()
    if len(train) == 0:
        raise ValueError('no target windows to adapt on')
    objective = FlatObjective(model)
    psi = objective.spec.flatten(init).detach().clone()
    centre = psi.clone() if anchor is None else objective.spec.flatten(anchor).detach()
    result = AdaptResult(params={})
    start = time.monotonic()

    def record():
        with torch.no_grad():
            result.train_loss.append(float(objective.loss(psi, train.u, train.y)))
            result.heldout_loss.append(float(objective.loss(psi, heldout.u, heldout.y))
                                       if len(heldout) else float('nan'))
        if not math.isfinite(result.train_loss[-1]):
            raise ValueError(f'adaptation loss turned non-finite at step '
                             f'{len(result.train_loss) - 1}')

    record()
    damping = MU_START
    for step in range(1, config.steps + 1):
        if config.rule == GAUSS_NEWTON:
            psi, rate, damping = lm_step(objective, psi, centre, train.u, train.y,
                                         config.gamma, damping, config.cg_steps)
        else:
            psi, rate = objective.armijo_step(psi, centre, train.u, train.y, config.lr,
                                              config.gamma)
        result.rates.append(rate)
        record()
        if progress is not None:
            progress(Progress(step, config.steps, result.heldout_loss[-1],
                              time.monotonic() - start))
    result.params = {k: v.clone() for k, v in objective.spec.unflatten(psi).items()}
    result.elapsed = time.monotonic() - start
    return result


def supervised(model: Nssm, train: Windows, heldout: Windows, config: AdaptConfig, seed: int,
               progress: Optional[ProgressFn] = None) -> AdaptResult:
    """The supervised baseline: the same steps from init_params(seed), gamma = 0."""
    dtype = next(model.parameters()).dtype
    return adapt(model, init_params(model.config, seed, dtype), train, heldout,
                 replace(config, gamma=0.0), progress)
