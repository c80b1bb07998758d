"""Percentile summaries of durations for the JSON lines of the soak and the benchmarks.

Percentiles interpolate linearly (numpy's default); the 100th is the maximum. No rclpy here.
"""
from typing import Dict, Sequence

import numpy as np

POINTS = (50, 99, 99.9, 100)


def percentiles(values: Sequence[float], points: Sequence[float] = POINTS, scale: float = 1.0,
                digits: int = 4, key: str = '{}') -> Dict[str, float]:
    """The percentiles `points` of values * scale, rounded to `digits` decimals.

    Args:
        values: shape [n], e.g. durations in s; none: the result is {}.
        points: percentiles in [0, 100].
        scale: unit conversion, e.g. 1e3 for s -> ms.
        key: format of each key, filled with 'p50', 'p99', 'p999' (for 99.9), ... and 'max'
            (for 100), e.g. 'tick_{}_us' -> 'tick_p50_us'.

    Returns:
        {key: value} in the order of `points`.
    """
    v = np.asarray(values, dtype=float) * scale
    if v.size == 0:
        return {}
    return {key.format(_name(p)): round(float(q), digits)
            for p, q in zip(points, np.percentile(v, points))}


def _name(point: float) -> str:
    return 'max' if point == 100 else 'p' + f'{point:g}'.replace('.', '')
