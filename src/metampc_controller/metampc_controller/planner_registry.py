"""The controller's planners by name: the `planner` parameter's choices and their factories.

A :class:`PlannerKind` says how a planner is built (outside the tick) from the controller's
config (:class:`~metampc_controller.controller_params.ControllerConfig`: its ``mpc`` section,
and the NMPC's ``nmpc_tail`` and ``nmpc_solver``) and the model it predicts with, and which model
that is: the learned NSSM (weights from the learner) or the plant's own equations (plant_info's
family and dt, the samples' theta). The controller looks its kind up once, at start.
"""
from dataclasses import dataclass
from typing import Any, Callable, Dict, NamedTuple, Sequence, Union

from metampc_model.latent_model import LatentModel
from metampc_model.narx_predictor import NarxPredictor
from metampc_model.predictor import NssmPredictor
from metampc_plant.family import PlantFamily
from metampc_controller.local_mpc import LocalLinearMpc
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_controller.planner import Planner


class TrueModel(NamedTuple):
    """The plant's equations as a planner predicts with them: family, theta, sample time
    dt (s)."""

    family: PlantFamily
    theta: Sequence[float]
    dt: float


@dataclass(frozen=True)
class PlannerKind:
    """One planner of the registry.

    Attributes:
        build: (controller config, model) -> a planner (ValueError if the model does not
            fit). model: a
            :class:`~metampc_model.latent_model.LatentModel` where `learned`, else a
            :class:`TrueModel`.
        learned: plans on the NSSM the learner sends (the controller subscribes to its
            weights, encodes z_t for it, checks and swaps models, may ask for adaptation);
            else on the plant's equations (theta from the samples, :meth:`Nmpc.set_theta`).
        waiting: the solver status of a tick before that model is there (the pre-model input
            answers).
    """

    build: Callable[[Any, Any], Planner]
    learned: bool
    waiting: str


def latent_mpc(config: MpcConfig, model: LatentModel) -> LatentMpc:
    """The latent MPC of `config` on a model: the QP, its OSQP set-up and the DARE terminal
    cost (milliseconds: outside the tick). ValueError if the model does not fit."""
    mpc = LatentMpc(config)
    mpc.set_model(model)
    return mpc


def learned_mpc(config: MpcConfig, predictor: Union[NssmPredictor, NarxPredictor]
                ) -> Union[LatentMpc, LocalLinearMpc]:
    """The planner of a learned model of either class: the latent MPC on an NSSM's latent
    model (:func:`latent_mpc`), or on a feature NARX the same QP on its linearisation at the
    current state, rebuilt each tick (:class:`~metampc_controller.local_mpc.LocalLinearMpc`,
    offset-free none). ValueError if the model does not fit."""
    if isinstance(predictor, NarxPredictor):
        return LocalLinearMpc(config, predictor)
    return latent_mpc(config, predictor.latent)


def nmpc(config: MpcConfig, model: TrueModel, tail: int = 0, solver: str = 'ipopt') -> Nmpc:
    """The NMPC of `config`'s horizon, weights and bounds, a `tail` (samples) and a `solver`
    on the plant's equations (ipopt: its NLP built on CasADi, about 0.1-0.5 s, outside the
    tick). ValueError if theta does not fit the family."""
    return Nmpc(NmpcConfig(**config.shared(), dt=model.dt, tail=tail, solver=solver),
                model.family, model.theta)


REGISTRY: Dict[str, PlannerKind] = {
    'latent_mpc': PlannerKind(lambda config, model: latent_mpc(config.mpc, model),
                              learned=True, waiting='no_model'),
    'nmpc': PlannerKind(lambda config, model: nmpc(config.mpc, model, config.nmpc_tail,
                                                   config.nmpc_solver),
                        learned=False, waiting='no_plant_info'),
}


def planner_kind(name: str) -> PlannerKind:
    """The registry's entry for `name`; ValueError (one line, the names known) if none."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f'unknown planner {name!r} (known: {", ".join(REGISTRY)})') from None


__all__ = ['TrueModel', 'PlannerKind', 'REGISTRY', 'planner_kind', 'latent_mpc', 'learned_mpc',
           'nmpc']
