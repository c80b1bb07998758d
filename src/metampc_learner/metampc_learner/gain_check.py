"""The gain check: an adapted model must agree in sign with its own samples' linear fit.

Before the learner publishes an adapted model (Adapt service, ``gain_check`` on), the
steady-state gain of its latent model on the family's tracked outputs
(:mod:`metampc_model.steady_gain`) is held against that of the ARX fitted by least squares on
the same training samples (:mod:`metampc_learner.arx`). Where ``eig(G_arx G_m^+)`` has a real
part <= 0 the model's gain has the wrong sign along a direction, and the offset-free MPC's
integral action drives the plant away along it (docs/mpc.md): the model is refused and the
ARX flies in its place, the Adapt answer's ``fallback`` says so. No threshold to tune: the
sign is the condition of integral controllability. Why and measured: docs/learner.md.
"""
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from metampc_model.latent_model import LatentModel
from metampc_model.steady_gain import agreement, steady_gain


@dataclass
class GainVerdict:
    """The check's answer.

    Attributes:
        ok: the model may fly (also when the check cannot be made: `reason` says why).
        eigs: eig(G_arx G_m^+) on the tracked outputs (complex; empty when unchecked).
        reason: one line.
    """

    ok: bool
    eigs: np.ndarray
    reason: str


def gain_verdict(model: LatentModel, reference: LatentModel,
                 tracked: Sequence[int]) -> GainVerdict:
    """Verdict on `model` against `reference` (the ARX of the same samples) on the output
    rows `tracked` (module docstring)."""
    gains = []
    for name, latent in (('the model', model), ('the ARX', reference)):
        try:
            gains.append(steady_gain(latent))
        except ValueError as err:
            return GainVerdict(True, np.zeros(0, complex), f'gain check: unchecked, {name}: {err}')
    eigs = agreement(gains[1], gains[0], tracked)
    text = ', '.join(f'{v.real:.3g}' + (f'{v.imag:+.3g}j' if abs(v.imag) > 1e-12 else '')
                     for v in eigs)
    if np.all(eigs.real > 0.0):
        return GainVerdict(True, eigs, f'gain check passed: eig(G_arx G_m^+) = {text} on '
                                       f'outputs {list(tracked)}')
    return GainVerdict(False, eigs, f'gain check: its steady-state gain on outputs '
                                    f'{list(tracked)} disagrees in sign with the least-squares '
                                    f'ARX of its samples (eig(G_arx G_m^+) = {text})')


__all__ = ['gain_verdict', 'GainVerdict']
