"""An independent held-out set of the target system, and l_SSM of a published model on it.

The experiment report ranks the methods on this set, not on the learner's own held-out 60 of
~300 buffered samples: at least :data:`HELDOUT_SAMPLES` samples of theta* in fresh bounded
excitation episodes simulated with the plant core (``data.simulate_target``) at the learner's
source excitation settings and the plant's dt, substeps, bounds and state box, seeded by
:func:`heldout_seed` (``SeedSequence([s, HELDOUT_STREAM])``: shares nothing with the run's
collection). Each model is scored in its own normalisation and architecture (the decoded
NssmWeights) on windows of H + T samples with ``nssm.prediction_loss`` (l_SSM of eq. (SSM),
normalised units); a feature NARX on the same T predicted samples of each window (its p lags
the window's last). How it enters the report: docs/experiments.md. No rclpy here.
"""
import math
from dataclasses import replace
from typing import List, Mapping, Sequence, Union

import numpy as np
import torch

from metampc_model.nssm import Nssm, prediction_loss, torch_params
from metampc_model.feature_narx import FeatureNarx
from metampc_model.weights_codec import DecodedNarx, DecodedWeights
from metampc_learner import narx_learning
from metampc_learner.data import simulate_target, SourceConfig, Trajectory, Windows

HELDOUT_SAMPLES = 2000
HELDOUT_STREAM = 0x4e1d
# Episodes simulated per one needed: at most 14 % of the excitation episodes escape for
# theta in [-3.5, 3.5] (measured, default source; the worst near theta = -0.25).
ATTEMPTS_PER_EPISODE = 4


def heldout_seed(run_seed: int) -> int:
    """The held-out set's seed for the run `run_seed` (see the module docstring)."""
    state = np.random.SeedSequence([int(run_seed), HELDOUT_STREAM]).generate_state(1, np.uint64)
    return int(state[0])


def plant_source(source: SourceConfig, dt: float, substeps: int, u_min: Sequence[float],
                 u_max: Sequence[float], state_bound: float) -> SourceConfig:
    """The source settings with the target plant's sampling (dt s, RK4 substeps), input bounds
    (one per input) and state box, as the learner simulates the target for its oracle."""
    return replace(source, dt=float(dt), substeps=int(substeps), state_bound=float(state_bound),
                   excitation=replace(source.excitation,
                                      u_min=tuple(np.atleast_1d(u_min).astype(float)),
                                      u_max=tuple(np.atleast_1d(u_max).astype(float))))


def target_heldout(theta: Sequence[float], source: SourceConfig, run_seed: int,
                   n_samples: int = HELDOUT_SAMPLES) -> List[Trajectory]:
    """`n_samples` samples of the system theta in bounded episodes of
    ``source.episode_samples`` (the last one shortened), physical units, seeded by
    :func:`heldout_seed` (run_seed).

    Raises:
        RuntimeError: too many episodes left the state box.
    """
    episodes = math.ceil(n_samples / source.episode_samples)
    return simulate_target(theta, source, n_samples, heldout_seed(run_seed),
                           max_attempts=ATTEMPTS_PER_EPISODE * episodes)


def heldout_loss(model: Nssm, params: Mapping[str, torch.Tensor], windows: Windows) -> float:
    """l_SSM of eq. (SSM) of `params` averaged over normalised windows u (N, H+T, n_u),
    y (N, H+T, n_y): mean over windows and T steps of the squared error summed over outputs
    (normalised units); nan without windows."""
    if len(windows) == 0:
        return math.nan
    with torch.no_grad():
        return float(prediction_loss(model, params, windows.u, windows.y))


def model_heldout_loss(weights: Union[DecodedWeights, DecodedNarx],
                       trajectories: List[Trajectory], loss_horizon: int,
                       history: int = 0) -> float:
    """l_SSM of a decoded model on windows of H + `loss_horizon` samples of `trajectories`
    (physical units), normalised with the model's own normalisation; a feature NARX's: its
    T-step rollout loss from every state of p samples (:func:`narx_learning.heldout_loss`)
    after each trajectory's first `history` - p, so that it predicts the samples an NSSM of
    H = `history` predicts (0: from the start).

    The message carries no T, so the learner's is passed; the published A is the effective
    one (bounded already when ``stable_latent``), so the parameters are used as they are.
    """
    if isinstance(weights, DecodedNarx):
        params = {k: torch.from_numpy(v.astype(np.float64)) for k, v in weights.params.items()}
        skip = max(int(history) - weights.shape.order, 0)
        return narx_learning.heldout_loss(FeatureNarx(weights.shape, weights.norm, params),
                                          [(t.u[skip:], t.y[skip:]) for t in trajectories],
                                          int(loss_horizon))
    config = replace(weights.config, loss_horizon=int(loss_horizon))
    windows = Windows.from_trajectories(trajectories, weights.norm, config)
    return heldout_loss(Nssm(config, weights.norm), torch_params(weights.params), windows)


__all__ = ['HELDOUT_SAMPLES', 'HELDOUT_STREAM', 'heldout_seed', 'plant_source', 'target_heldout',
           'heldout_loss', 'model_heldout_loss']
