"""Seeded excitation inputs for data collection, each within [u_min, u_max].

The controller's input before a model (``pre_model_input: excitation``) and the learner's
simulated episodes (source tasks, the oracle, the warm-up of online collection) draw from here.

Every generator returns an array of shape (B, K, n_u): K input vectors for each of B systems,
one per sample of length dt, each input within its own bounds (n_u = the number of bounds).
The inputs of one system are drawn independently of each other, within the band
``center +- amplitude (u_max - u_min) / 2`` of each input (default: the whole range). Determinism:
the same arguments and seed give the same array; with one input the draws are those of a (B, K)
array.
"""
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from metampc_common.params import check_fields, param

KINDS = ('random_hold', 'multisine', 'prbs')


def amplitude_param():
    """The band's width as a parameter field (the learner's and the controller's)."""
    return param(1.0, 'excitation within center +- amplitude x half of each input range (1 '
                      'about the middle: the whole range)', gt=0, le=1)


def center_param():
    """The band's centre as a parameter field (the learner's and the controller's)."""
    return param((), 'centre of the excitation band, one per input (empty: the middle of each '
                     'input range); the band must lie within the input bounds', item=float,
                 scalar=True)


@dataclass
class ExcitationConfig:
    """Settings of an excitation signal.

    Attributes:
        kind: 'random_hold' (uniform levels held for hold_s; band-limited to ~1/hold_s Hz),
            'multisine' (sum of sines with random phases up to f_max_hz) or
            'prbs' (pseudo-random binary sequence switching at most every hold_s).
        u_min, u_max: bounds the signal respects, one per input (a number: one input). Empty
            means "the plant family's"; they must be filled in (e.g. by the learner's source
            settings) before a signal is generated.
        hold_s: hold time of random_hold and prbs, s.
        amplitude, center: the band the signal keeps to, per input
            ``center +- amplitude (u_max - u_min) / 2`` (center empty: the middle), e.g. an
            operating region inside wide bounds.
        f_max_hz: highest frequency of multisine, Hz.
        n_sines: number of multisine components.
    """

    kind: str = param('random_hold', 'source excitation', choices=KINDS)
    u_min: Tuple[float, ...] = param((), "input lower bounds of the simulated systems, one per "
                                         "input (empty: the family's)", item=float, scalar=True)
    u_max: Tuple[float, ...] = param((), "input upper bounds of the simulated systems, one per "
                                         "input (empty: the family's)", item=float, scalar=True)
    hold_s: float = param(0.5, 'excitation hold time, s', gt=0)
    amplitude: float = amplitude_param()
    center: Tuple[float, ...] = center_param()
    f_max_hz: float = 1.0
    n_sines: int = 8

    def band(self) -> Tuple[np.ndarray, np.ndarray]:
        """(lo, hi), each (n_u,): the band the signal keeps to (bounds filled in).

        Raises:
            ValueError: a centre of the wrong length, or a band that leaves the bounds.
        """
        lo, hi = np.asarray(self.u_min, dtype=float), np.asarray(self.u_max, dtype=float)
        if self.amplitude == 1.0 and not self.center:
            return lo, hi              # the whole range, exactly (no rounding of the draws)
        half = self.amplitude * 0.5 * (hi - lo)
        center = 0.5 * (lo + hi) if not self.center else np.asarray(self.center, dtype=float)
        if center.shape != lo.shape:
            raise ValueError(f'excitation_center needs one value per input ({lo.size}), got '
                             f'{list(self.center)}')
        slack = 1e-9 * (1.0 + np.abs(hi - lo))        # the rounding of center +- half
        if np.any(center - half < lo - slack) or np.any(center + half > hi + slack):
            raise ValueError(f'the excitation band, excitation_center {center.tolist()} +- '
                             f'excitation_amplitude x half the range {half.tolist()}, leaves '
                             f'the input bounds [{lo.tolist()}, {hi.tolist()}]')
        return np.maximum(center - half, lo), np.minimum(center + half, hi)

    def validate(self) -> None:
        """Raise ValueError if a setting is out of range."""
        check_fields(self)
        # One side may still be empty ("the family's"); excitation() needs both.
        filled = self.u_min and self.u_max
        if filled and (len(self.u_min) != len(self.u_max) or any(
                lo > hi for lo, hi in zip(self.u_min, self.u_max))):
            raise ValueError(f'need u_min <= u_max, one pair per input, got {list(self.u_min)}, '
                             f'{list(self.u_max)}')
        if filled:
            self.band()
        if not (self.f_max_hz > 0 and self.n_sines >= 1):
            raise ValueError('f_max_hz must be > 0 and n_sines >= 1')


def excitation(config: ExcitationConfig, batch: int, n_samples: int, dt: float,
               seed: int) -> np.ndarray:
    """Generate inputs of shape (batch, n_samples, n_u) for sample time dt (s), seeded."""
    config.validate()
    if not (config.u_min and config.u_max):
        raise ValueError("excitation bounds are not set (empty: fill in the family's)")
    if batch < 0 or n_samples < 0 or not dt > 0:
        raise ValueError(f'need batch, n_samples >= 0 and dt > 0 s, got {batch}, {n_samples}, '
                         f'{dt}')
    lo, hi = config.band()
    n_u = lo.shape[0]
    if n_samples == 0:
        return np.zeros((batch, 0, n_u))
    rng = np.random.default_rng(seed)
    hold = max(1, int(round(config.hold_s / dt)))
    n_levels = -(-n_samples // hold)
    if config.kind == 'random_hold':
        levels = rng.uniform(lo, hi, size=(batch, n_levels, n_u))
        return np.repeat(levels, hold, axis=1)[:, :n_samples]
    if config.kind == 'prbs':
        bits = rng.integers(0, 2, size=(batch, n_levels, n_u))
        return np.repeat(np.where(bits == 1, hi, lo), hold, axis=1)[:, :n_samples].astype(float)
    t = np.arange(n_samples) * dt
    freqs = np.linspace(config.f_max_hz / config.n_sines, config.f_max_hz, config.n_sines)
    phases = rng.uniform(0, 2 * np.pi, size=(batch, n_u, config.n_sines, 1))
    s = np.sin(2 * np.pi * freqs[:, None] * t[None, :] + phases).sum(axis=2)  # (B, n_u, K)
    peak = np.abs(s).max(axis=2, keepdims=True)
    s = np.swapaxes(s / np.where(peak > 0, peak, 1.0), 1, 2)                # (B, K, n_u)
    # |s| <= 1 exactly, but the affine map can round one ulp past a bound.
    return np.clip(0.5 * (lo + hi) + 0.5 * (hi - lo) * s, lo, hi)
