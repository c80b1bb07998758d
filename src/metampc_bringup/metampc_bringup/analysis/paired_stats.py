"""Paired comparison of two per-seed samples: does the claim "a < b" (lower is better: a loss, a
tracking cost) hold across seeds, and how surely?

:func:`paired_claim` takes the pairs (a_i, b_i), one per seed, and gives the number of seeds
where a_i < b_i, the median paired difference (``log=True``: of log a - log b, read as the
ratio a/b) with a percentile-bootstrap 95 % interval (pairs resampled), the two-sided Wilcoxon
signed-rank p-value and the verdict: *supported* when the interval lies below 0 (ratio 1),
*contradicted* when above. A pair with a NaN is dropped; inf (an escaped run) is the worst
value and keeps its place (order statistics, no interpolation; ties leave the test).
How to read it: docs/experiments.md. No rclpy here.
"""
import math
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np
from scipy.stats import wilcoxon

CONFIDENCE = 0.95
JsonFloat = Union[float, str, None]


def paired_claim(a: Sequence[float], b: Sequence[float], n_boot: int = 10000, seed: int = 0,
                 log: bool = False) -> Dict[str, Any]:
    """Statistics of the claim "a < b" over the pairs (a[i], b[i]), one per seed.

    Args:
        a, b: per-seed values of equal length; NaN = missing, inf = failed (escaped).
        n_boot: bootstrap resamples of the pairs.
        seed: seed of the numpy Generator of the resamples (same seed, same interval).
        log: compare log a - log b (values must be >= 0; 0 has log -inf), see the module.

    Returns:
        A JSON-safe dict: ``n`` (pairs used, both values present), ``dropped`` (pairs with a
        NaN), ``holds`` (pairs with a < b), ``log``, ``median_diff``, ``ci_low``, ``ci_high``
        (median difference and its 95 % interval, of the logs when `log`), with `log` also
        ``median_ratio``, ``ratio_ci_low``, ``ratio_ci_high`` (their exponentials: a/b),
        ``p_wilcoxon`` (two-sided; None when n < 2 or no pair differs), ``supported``
        (ci_high < 0) and ``contradicted`` (ci_low > 0), both False when n < 2. Floats: NaN
        (undefined, n < 2) is None, +-inf the strings 'inf' and '-inf' (strict JSON has no
        inf and null would lose the sign; float() reads them).
    """
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f'paired samples of equal length expected, got {x.shape}, {y.shape}')
    keep = ~(np.isnan(x) | np.isnan(y))
    x, y = x[keep], y[keep]
    if log:
        if np.any(x < 0) or np.any(y < 0):
            raise ValueError('log=True needs values >= 0')
        with np.errstate(divide='ignore'):
            x, y = np.log(x), np.log(y)
    with np.errstate(invalid='ignore'):     # inf - inf: a tie, set below
        d = np.where(x == y, 0.0, x - y)
    n = int(d.size)
    median = float(_medians(d)) if n else math.nan
    low, high = _bootstrap(d, n_boot, seed) if n >= 2 else (math.nan, math.nan)
    out: Dict[str, Any] = {
        'n': n, 'dropped': int(keep.size - n), 'holds': int(np.sum(x < y)), 'log': log,
        'median_diff': _json(median), 'ci_low': _json(low), 'ci_high': _json(high),
        'p_wilcoxon': _json(float(wilcoxon(d).pvalue)
                            if n >= 2 and np.any(d != 0) else math.nan),
        'supported': bool(high < 0), 'contradicted': bool(low > 0)}
    if log:
        with np.errstate(over='ignore'):
            ratios = np.exp([median, low, high])
        out.update(zip(('median_ratio', 'ratio_ci_low', 'ratio_ci_high'),
                       (_json(float(r)) for r in ratios)))
    return out


def claim_cells(stats: Dict[str, Any]) -> Tuple[str, str, str, str]:
    """Table cells of :func:`paired_claim`'s result: holds (``7/10``, with the missing pairs),
    estimate with its interval (the ratio when `log`), p-value, verdict."""
    holds = f"{stats['holds']}/{stats['n']}" + (
        f", {stats['dropped']} missing" if stats['dropped'] else '')
    keys = ('median_ratio', 'ratio_ci_low', 'ratio_ci_high') if stats['log'] else (
        'median_diff', 'ci_low', 'ci_high')
    median, low, high = (_num(stats[k]) for k in keys)
    estimate = _g(median) + ('' if math.isnan(low) else f' [{_g(low)}, {_g(high)}]')
    verdict = ('supported' if stats['supported'] else
               'contradicted' if stats['contradicted'] else 'not supported')
    return holds, estimate, _g(_num(stats['p_wilcoxon']), 2), verdict


def format_claim(stats: Dict[str, Any]) -> str:
    """One line (a markdown cell) of :func:`paired_claim`'s result, e.g.
    ``7/10; median ratio 0.81 [0.62, 0.95]; p = 0.02; supported``."""
    holds, estimate, p, verdict = claim_cells(stats)
    kind = 'median ratio' if stats['log'] else 'median diff'
    return f'{holds}; {kind} {estimate}; p = {p}; {verdict}'


def median_ci(values: Sequence[float], n_boot: int = 10000, seed: int = 0
              ) -> Tuple[float, float, float]:
    """One sample's median and the percentile-bootstrap 95 % interval of it (values
    resampled, endpoints as in :func:`paired_claim`, so inf (a failed run) stays inf); the
    interval is NaN with fewer than 2 values, everything NaN with none."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        return math.nan, math.nan, math.nan
    low, high = _bootstrap(x, n_boot, seed) if x.size >= 2 else (math.nan, math.nan)
    return float(_medians(x)), low, high


def _medians(d: np.ndarray) -> np.ndarray:
    """Medians along the last axis on the extended reals (see the module)."""
    s = np.sort(d, axis=-1)
    n = s.shape[-1]
    low, high = s[..., (n - 1) // 2], s[..., n // 2]
    with np.errstate(invalid='ignore'):     # -inf + inf, replaced by 0
        return np.where(low == -high, 0.0, 0.5 * low + 0.5 * high)


def _bootstrap(d: np.ndarray, n_boot: int, seed: int) -> Tuple[float, float]:
    """Percentile interval of the median of `d` over `n_boot` resamples; the endpoints are
    order statistics of the resampled medians, the outer ones of the two bracketing the
    quantile (never an interpolation, which inf would turn into NaN)."""
    idx = np.random.default_rng(seed).integers(0, d.size, size=(n_boot, d.size))
    medians = _medians(d[idx])
    tail = (1 - CONFIDENCE) / 2
    return (float(np.quantile(medians, tail, method='lower')),
            float(np.quantile(medians, 1 - tail, method='higher')))


def _json(x: float) -> JsonFloat:
    if math.isnan(x):
        return None
    return ('inf' if x > 0 else '-inf') if math.isinf(x) else x


def _num(x: Optional[Union[float, str]]) -> float:
    """A float of :func:`_json`'s encoding (NaN also as itself: JSON-safe data may have been
    restored to floats)."""
    return math.nan if x is None else float(x)


def _g(x: float, digits: int = 3) -> str:
    return 'n/a' if math.isnan(x) else f'{x:.{digits}g}'
