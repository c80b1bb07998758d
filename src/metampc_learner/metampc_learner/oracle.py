"""The oracle: an NSSM fit from a random initialisation on plentiful data of the target itself.

The yardstick of the comparison: ``episodes`` bounded excitation episodes of the target plant,
simulated with the plant core at the plant's own theta, dt, substeps, input bounds and state
box (escaped episodes dropped), then ``steps`` Adam steps on minibatches of ``batch_windows``
windows of l_SSM (eq. (SSM)) from ``init_params(seed)``. Loss curves (normalised units) have
``steps + 1`` entries, before the first step and after every step: held-out loss on the given
windows, training loss on at most ``eval_windows`` training windows. Why Adam: docs/learner.md.
"""
import time
from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
import torch

from metampc_common.params import check_fields, param
from metampc_model.nssm import Nssm, Params
from metampc_learner.adapt import AdaptResult
from metampc_learner.data import simulate_episodes, SourceConfig, Trajectory, Windows
from metampc_learner.objective import FlatObjective
from metampc_learner.progress import Progress, ProgressFn


@dataclass
class OracleConfig:
    """Attributes: episodes simulated, Adam steps, Adam lr, windows per step, evaluation subset
    size of the training loss."""

    episodes: int = param(100, 'simulated target episodes of the oracle', ge=1)
    steps: int = param(500, 'oracle Adam steps', ge=0, live=True)
    lr: float = param(3e-3, 'oracle Adam step size', gt=0, live=True)
    batch_windows: int = param(256, 'oracle windows per Adam step', ge=1)
    eval_windows: int = 1024

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)
        if self.eval_windows < 1:
            raise ValueError(f'eval_windows must be >= 1, got {self.eval_windows}')


def oracle_data(theta: Sequence[float], source: SourceConfig, episodes: int, seed: int
                ) -> List[Trajectory]:
    """`episodes` bounded excitation episodes of system theta (n_theta values; escaped ones
    dropped)."""
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    trajs, _ = simulate_episodes(np.tile(theta, (episodes, 1)), source, seed)
    return [t for t in trajs if t is not None]


def fit_oracle(model: Nssm, init: Params, train: Windows, heldout: Windows,
               config: OracleConfig, seed: int, progress: Optional[ProgressFn] = None
               ) -> AdaptResult:
    """Adam on minibatches of `train` from `init`; curves as in the module docstring.

    Raises:
        ValueError: no training windows, or the loss turned non-finite.
    """
    config.validate()
    if len(train) == 0:
        raise ValueError('no oracle windows to train on')
    objective = FlatObjective(model)
    psi = torch.nn.Parameter(objective.spec.flatten(init).detach().clone())
    optimiser = torch.optim.Adam([psi], lr=config.lr)
    gen = torch.Generator().manual_seed(int(seed))
    evaluate = torch.randperm(len(train), generator=gen)[:config.eval_windows]
    result = AdaptResult(params={})
    start = time.monotonic()

    def record(step: int) -> None:
        with torch.no_grad():
            result.train_loss.append(float(objective.loss(psi, train.u[evaluate],
                                                          train.y[evaluate])))
            result.heldout_loss.append(float(objective.loss(psi, heldout.u, heldout.y))
                                       if len(heldout) else float('nan'))
        if not np.isfinite(result.train_loss[-1]):
            raise ValueError(f'oracle loss turned non-finite at step {step}')

    record(0)
    for step in range(1, config.steps + 1):
        idx = torch.randint(len(train), (config.batch_windows,), generator=gen)
        optimiser.zero_grad(set_to_none=True)
        objective.loss(psi, train.u[idx], train.y[idx]).backward()
        optimiser.step()
        record(step)
        if progress is not None:
            progress(Progress(step, config.steps, result.heldout_loss[-1],
                              time.monotonic() - start))
    result.params = {k: v.detach().clone()
                     for k, v in objective.spec.unflatten(psi.detach()).items()}
    result.elapsed = time.monotonic() - start
    return result


__all__ = ['OracleConfig', 'oracle_data', 'fit_oracle']
