#!/usr/bin/env python3
"""Per seed and method of van der Pol run folders: tracking cost / NMPC, held-out l_SSM, the
latent consistency loss l_cons on the same held-out set (both normalised units; docs/learning.md)
and the adapted model's latent residual at rest (docs/mpc.md, "Why seed 4 failed").

At a set-point r the plant rests at x = (r, 0) under u = r; the encoder reads H samples of
that rest and ``rho = z - (A z + B u + e)`` (physical units, predictor.latent_model) says how
far its state is from a fixed point of the latent dynamics. Printed: ||rho|| (latent units,
comparable only within one model) and the output-space size
``sqrt(1/N sum_{k=0..N-1} ||C A^k rho||^2)`` over the controller's horizon N (physical units,
independent of the latent's coordinates), each the mean over the four set-points.

    python scripts/latent_residual.py RUN [RUN ...]
"""
import argparse
import json
import os

from dataclasses import replace

import numpy as np
import torch

from metampc_bringup.analysis.experiment_report import _messages, PLANT_INFO
from metampc_bringup.analysis.retrack import adapted_models, seed_recordings
from metampc_bringup.experiment_config import from_mapping, learner_config
from metampc_recording.recording_reader import read_recording
from metampc_model.nssm import consistency_loss, Nssm, torch_params
from metampc_model.predictor import NssmPredictor
from metampc_model.weights_codec import fields_of, weights_from_fields
from metampc_learner.data import Windows
from metampc_learner.heldout import plant_source, target_heldout

SET_POINTS = (0.8, -0.5, 0.3, -0.8)       # the paper's reference (setpoint_sequence's)


def rest_residuals(msg, horizon: int):
    """(mean ||rho||, mean output-space size) of an NssmWeights message at the set-points."""
    decoded = weights_from_fields(fields_of(msg))
    model = NssmPredictor(decoded.config, decoded.norm, decoded.params)
    h, lat = decoded.config.history, model.latent
    raw, out = [], []
    for r in SET_POINTS:
        u = np.full((h, 1), r)
        z = model.encode(u, np.tile([r, 0.0], (h, 1)))
        rho = z - lat.step(z, np.array([r]))
        raw.append(np.linalg.norm(rho))
        size, v = 0.0, rho
        for _ in range(horizon):
            size += float(np.sum((lat.C @ v) ** 2))
            v = lat.A @ v
        out.append(np.sqrt(size / horizon))
    return float(np.mean(raw)), float(np.mean(out))


def heldout_set(recording: str, experiment: dict, seed: int, theta):
    """The report's held-out trajectories of the seed (experiment_report.heldout_losses)."""
    learner = learner_config(from_mapping(experiment), seed)
    source, p = learner.source, _messages(read_recording(recording), PLANT_INFO)[-1]
    source = plant_source(source, p.dt, p.substeps, p.u_min, p.u_max, p.state_bound)
    return target_heldout(np.atleast_1d(theta), source, seed), learner.nssm.loss_horizon


def heldout_consistency(msg, trajectories, loss_horizon: int) -> float:
    """l_cons of the model on the held-out windows (normalised units)."""
    decoded = weights_from_fields(fields_of(msg))
    config = replace(decoded.config, loss_horizon=int(loss_horizon))
    windows = Windows.from_trajectories(trajectories, decoded.norm, config)
    with torch.no_grad():
        return float(consistency_loss(Nssm(config, decoded.norm), torch_params(decoded.params),
                                      windows.u, windows.y))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('runs', nargs='+', help='run folders of run_experiment.py')
    args = parser.parse_args()
    print('run | seed | theta* | method | cost / NMPC | held-out l_SSM | held-out l_cons | '
          '||rho|| at rest | output-space rho at rest')
    for run in args.runs:
        report = json.load(open(os.path.join(run, 'report.json')))
        horizon = int(report['config']['controller']['horizon'])
        recordings = seed_recordings(run)
        for seed, theta, per in zip(report['seeds'], report['thetas'], report['per_seed']):
            methods = per['methods']
            nmpc = methods['nmpc']['tracking']['tracking']['cost']
            models = adapted_models(recordings[seed])
            trajectories, n_t = heldout_set(recordings[seed], per['config'], seed, theta)
            for name in ('imaml', 'maml'):
                if name not in methods:
                    continue
                cost = methods[name]['tracking']['tracking']['cost']
                raw, out = rest_residuals(models[name], horizon)
                cons = heldout_consistency(models[name], trajectories, n_t)
                print(f'{os.path.basename(run)} | {seed} | {theta[0]:.3f} | {name} | '
                      f'{cost / nmpc:.3f} | {methods[name]["heldout"]["adapted"]:.5f} | '
                      f'{cons:.4f} | {raw:.3g} | {out:.3g}')


if __name__ == '__main__':
    main()
