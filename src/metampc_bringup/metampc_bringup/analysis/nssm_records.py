"""An NSSM on a measured record: the record's pairing, its windows, its free-run simulation.

A record (u (N,), y (N,)), physical, one input and one output, with u[k] the input that acts
first on y[k+1]. :func:`trajectory` pairs them so (the learner's Trajectory),
:func:`record_windows` cuts the NSSM's windows (H + T pairs) from them, and
:func:`simulate_nssm` runs the model over the whole record from its encoded initial state
(eq. z_next on the inputs alone). Used by the Cascaded Tanks benchmark
(:mod:`metampc_bringup.studies.cascaded_tanks`, docs/real_data.md). No ROS.
"""
import numpy as np
import torch

from metampc_learner.data import Trajectory, Windows
from metampc_model.nssm import Nssm, Params


def trajectory(u: np.ndarray, y: np.ndarray, start: int, stop: int) -> Trajectory:
    """Record samples start..stop-1 as a Trajectory: u[k] paired with the y[k+1] it acts on
    first (stop - start - 1 pairs)."""
    return Trajectory(np.arange(start, stop - 1), u[start:stop - 1], y[start + 1:stop])


def record_windows(model: Nssm, u: np.ndarray, y: np.ndarray, start: int, stop: int
                   ) -> Windows:
    """The NSSM's windows (H + T pairs) of record samples start..stop-1, normalised."""
    return Windows.from_trajectories([trajectory(u, y, start, stop)], model.norm, model.config,
                                     next(model.parameters()).dtype)


def simulate_nssm(model: Nssm, params: Params, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Free-run simulation over a record (N,): the encoder reads the H pairs (u[k], y[k+1]),
    k = 0..H-1, then the latent state runs on the inputs alone (eq. z_next) over one window of
    the whole record; y_hat[H+1..N-1], NaN at 0..H (not predicted)."""
    t = trajectory(u, y, 0, len(y))
    u_n, y_n = model.norm.normalise(t.u[None], t.y[None])
    dtype = next(model.parameters()).dtype
    with torch.no_grad():
        y_hat = torch.func.functional_call(model, params, (torch.as_tensor(u_n, dtype=dtype),
                                                           torch.as_tensor(y_n, dtype=dtype)))
    out = np.full(len(y), np.nan)
    out[model.config.history + 1:] = model.norm.denormalise_y(
        y_hat[0].double().numpy())[:, 0]
    return out
