"""A model fitted to D_target by a method: the one entry every adaptation goes through.

:func:`fit_target` fits `method` on the target's training trajectories: a meta method adapts
the meta-model by eq. (infer) (``adapt.adapt``), 'supervised' takes the same steps from random
weights, 'oracle' trains with Adam (``oracle.fit_oracle``), 'arx' fits the least-squares ARX
as an NSSM (:mod:`.arx`). With ``gain_check`` an adapted model whose steady-state gain
disagrees in sign with that ARX is refused and the ARX flies in its place
(:mod:`.gain_check`). A feature NARX is adapted in closed form, validated against the ARX of
its class (``narx_learning.adapt``). Used by the Adapt service, adapt_offline, the studies
and the benchmark. No rclpy. docs/learner.md.
"""
from dataclasses import dataclass, replace
import time
from typing import Optional, Sequence, Tuple, Union

import torch

from metampc_model.feature_narx import FeatureNarx
from metampc_model.nssm import init_params, Nssm, Params, prediction_loss
from metampc_model.predictor import latent_model
from metampc_learner import narx_learning
from metampc_learner.adapt import adapt, AdaptConfig, AdaptResult, supervised
from metampc_learner.arx import arx_nssm
from metampc_learner.data import Trajectory, Windows
from metampc_learner.gain_check import gain_verdict
from metampc_learner.oracle import fit_oracle, OracleConfig
from metampc_learner.progress import ProgressFn

SUPERVISED, ORACLE, ARX = 'supervised', 'oracle', 'arx'
BASELINES = (SUPERVISED, ORACLE, ARX)     # the methods that fit without a meta-model
NARX_ADAPT_METHODS = (*narx_learning.NARX_METHODS, ARX, ORACLE)   # a feature NARX's
LEAST_SQUARES = 'least_squares'         # the rule of a feature NARX's arx


class FitError(ValueError):
    """A fit that cannot be made (the ARX: too few samples, an order it cannot write)."""


@dataclass
class FitSettings:
    """How :func:`fit_target` fits (the learner node's parameters, resolved per request).

    Attributes:
        adapt: steps, lr, gamma, rule, cg_steps of eq. (infer) and the supervised baseline.
        oracle: the oracle's Adam settings (its steps and lr the request's).
        arx_order: p of the ARX (the arx method and the gain check's reference).
        gain_check: refuse an adapted model of the wrong gain sign (module docstring).
        tracked: the family's tracked outputs, on which the gain check compares.
        seed: initial weights of supervised and oracle, the oracle's minibatches.
        narx_gamma: ridge strength of a feature NARX's closed-form adaptation.
        narx_horizon: T of a feature NARX's held-out rollout loss, samples.
    """

    adapt: AdaptConfig
    oracle: OracleConfig
    arx_order: int
    gain_check: bool
    tracked: Tuple[int, ...]
    seed: int
    narx_gamma: float
    narx_horizon: int


@dataclass
class TargetFit:
    """What :func:`fit_target` made.

    Attributes:
        model: the model that flies (architecture and normalisation; a FeatureNarx holds its
            params too).
        result: the fit's curves (held-out loss index 0 before the first step; a feature NARX:
            [the meta-model's, the model's]; the arx: its own only) and, as `params`, the
            weights of the model that flies.
        train_loss, heldout_loss: the flying model's final losses (normalised units).
        steps: steps that made the flying model (0: least squares, closed form, or the ARX
            in the adapted model's place).
        gain_check: the gain check's verdict, one line ('' when not checked).
        replaced_by: 'arx' when the ARX flies in the adapted model's place, else ''
            (the Adapt answer's ``fallback``).
        rule: a feature NARX's closed-form rule (``AdaptedNarx.rule``, 'least_squares' for the
            arx); '' for an NSSM.
    """

    model: Union[Nssm, FeatureNarx]
    result: AdaptResult
    train_loss: float
    heldout_loss: float
    steps: int
    gain_check: str = ''
    replaced_by: str = ''
    rule: str = ''


def fit_target(method: str, model: Union[Nssm, FeatureNarx], start: Optional[Params],
               train: Sequence[Trajectory], held: Sequence[Trajectory], settings: FitSettings,
               progress: Optional[ProgressFn] = None) -> TargetFit:
    """Fit `method` (a meta method, or one of BASELINES) on `train`, score it on `held`
    (physical trajectories; the oracle's `train`: its simulated episodes).

    `model` gives the architecture and normalisation (a meta method: of the meta-model
    `start`; a feature NARX: the meta-model itself, or the base of its arx).

    Raises:
        FitError: the ARX cannot be fitted (the arx method).
        ValueError: no training windows, or a loss turned non-finite.
    """
    if isinstance(model, FeatureNarx):
        return _fit_narx(method, model, train, held, settings)
    if method == ARX:
        try:
            arx, result = _arx(model, train, held, settings.arx_order)
        except ValueError as err:
            raise FitError(f'arx: {err}') from None
        return TargetFit(arx, result, result.train_loss[-1], result.heldout_loss[-1], 0)
    dtype = next(iter(start.values())).dtype if start else next(model.parameters()).dtype
    train_w, held_w = (Windows.from_trajectories(part, model.norm, model.config, dtype)
                       for part in (train, held))
    if method == ORACLE:
        result = fit_oracle(model, init_params(model.config, settings.seed, dtype), train_w,
                            held_w, settings.oracle, settings.seed, progress)
        return TargetFit(model, result, result.train_loss[-1], result.heldout_loss[-1],
                         settings.oracle.steps)
    if method == SUPERVISED:
        result = supervised(model, train_w, held_w, settings.adapt, settings.seed, progress)
    else:
        result = adapt(model, start, train_w, held_w, settings.adapt, progress)
    fitted = TargetFit(model, result, result.train_loss[-1], result.heldout_loss[-1],
                       settings.adapt.steps)
    return _gain_checked(fitted, train, held, settings) if settings.gain_check else fitted


def _arx(base: Nssm, train: Sequence[Trajectory], held: Sequence[Trajectory], order: int
         ) -> Tuple[Nssm, AdaptResult]:
    """ARX(`order`) fitted on `train`, as an NSSM of `base`'s history, widths and stds
    (``arx.arx_nssm``), and its l_SSM on `train` and on `held` (one point each, the curves of
    a fit without steps). ValueError: see ``arx.arx_nssm``."""
    start = time.monotonic()
    config, norm, params = arx_nssm(train, order, base.config, base.norm)
    model = Nssm(config, norm)
    with torch.no_grad():
        losses = [float(prediction_loss(model, params, w.u, w.y)) for w in (
            Windows.from_trajectories(part, norm, config) for part in (train, held))]
    return model, AdaptResult(params, [losses[0]], [losses[1]], [], time.monotonic() - start)


def _gain_checked(fitted: TargetFit, train: Sequence[Trajectory], held: Sequence[Trajectory],
                  settings: FitSettings) -> TargetFit:
    """`fitted` with the gain check's verdict against the ARX of its training samples; the
    ARX in its place where refused (the curves stay the adaptation's)."""
    model, result = fitted.model, fitted.result
    try:
        arx, reference = _arx(model, train, held, settings.arx_order)
    except ValueError as err:
        return replace(fitted, gain_check=f'gain check: unchecked, the ARX: {err}')
    verdict = gain_verdict(latent_model(result.params, model.norm),
                           latent_model(reference.params, arx.norm), settings.tracked)
    if verdict.ok:
        return replace(fitted, gain_check=verdict.reason)
    return TargetFit(arx, replace(result, params=reference.params,
                                  elapsed=result.elapsed + reference.elapsed),
                     reference.train_loss[-1], reference.heldout_loss[-1], 0, verdict.reason,
                     ARX)


def _fit_narx(method: str, meta: FeatureNarx, train: Sequence[Trajectory],
              held: Sequence[Trajectory], settings: FitSettings) -> TargetFit:
    """A feature NARX: 'arx' the least-squares ARX(p) of the samples in its class
    (``narx_learning.arx_model``), any other method the closed-form adaptation of the
    meta-model `meta` (``narx_learning.adapt``, validated against that ARX)."""
    start = time.monotonic()
    records = [(t.u, t.y) for t in train]
    held_records = [(t.u, t.y) for t in held]
    horizon = settings.narx_horizon
    if method == ARX:
        model, rule = narx_learning.arx_model(meta, records), LEAST_SQUARES
        curve = [narx_learning.heldout_loss(model, held_records, horizon)]
    else:
        adapted = narx_learning.adapt(meta, records, settings.narx_gamma)
        model, rule = adapted.model, adapted.rule
        curve = [narx_learning.heldout_loss(m, held_records, horizon) for m in (meta, model)]
    loss = narx_learning.one_step_loss(model, records)
    result = AdaptResult(params=model.params, train_loss=[loss], heldout_loss=curve,
                         elapsed=time.monotonic() - start)
    return TargetFit(model, result, loss, curve[-1], 0, rule=rule)


__all__ = ['SUPERVISED', 'ORACLE', 'ARX', 'BASELINES', 'NARX_ADAPT_METHODS', 'LEAST_SQUARES',
           'FitError', 'FitSettings', 'TargetFit', 'fit_target']
