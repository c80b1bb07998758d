"""A real plant's twin: the experiment's tracking run on the family at a fitted theta.

A model identified on a real record cannot fly on the real plant here; its twin is the plant
family at the grey-box parameters fitted to that record, started at the fit's initial state.
:func:`twin_experiment` makes the twin the experiment's target (theta* = the fit, track_x0 =
its x(0), so the set-points of ``reference_inputs`` are the twin's steady states);
:func:`track_twin` flies NSSMs fitted to the record (the latent MPC of the experiment's
controller section) and the true-model NMPC, the yardstick, on it
(:func:`retrack.track_models`). No ROS. Used by studies/cascaded_tanks_run.py.
"""
from dataclasses import replace
from typing import Dict, Mapping, Optional, Sequence

from metampc_bringup.analysis.retrack import MethodResult, track_models
from metampc_bringup.experiment_config import ExperimentConfig
from metampc_controller.closed_loop import Episode
from metampc_model.nssm import Nssm, Params
from metampc_model.weights_codec import DecodedWeights, fields_from_weights, weights_from_fields


def twin_experiment(experiment: ExperimentConfig, theta: Sequence[float],
                    x0: Sequence[float]) -> ExperimentConfig:
    """The experiment with the twin as its target: theta* = `theta` (n_theta,), every
    tracking run from `x0` (n_x,), in the family's units."""
    return replace(experiment, theta=[float(v) for v in theta],
                   track_x0=[float(v) for v in x0])


def nssm_weights(model: Nssm, params: Params) -> DecodedWeights:
    """An NSSM's weights as the controller receives them (float32, through the message's
    fields; WeightsError if they do not describe a usable NSSM)."""
    return weights_from_fields(fields_from_weights(model.config, model.norm, params))


def track_twin(experiment: ExperimentConfig, theta: Sequence[float], x0: Sequence[float],
               models: Mapping[str, Optional[DecodedWeights]],
               episodes: Optional[Dict[str, Episode]] = None) -> Dict[str, MethodResult]:
    """The experiment's tracking run on the twin (theta, x0) flown by each of `models`: the
    latent MPC on the weights, the true-model NMPC for None. `episodes`, if given, receives
    each :class:`Episode`."""
    twin = twin_experiment(experiment, theta, x0)
    return track_models(twin, twin.first_seed, {}, models, episodes)
