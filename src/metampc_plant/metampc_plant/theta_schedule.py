"""A plant whose parameters change while it runs: theta as steps and ramps over plant time.

Pure Python (no rclpy). A schedule is a list of segments ``(t_start, t_end, theta_end)`` over
the plant time t = k dt of an episode (k restarts at 0 with every reset): before the first
segment theta is the episode's; over a segment it goes linearly to ``theta_end`` (``t_end ==
t_start``: a step) and stays until the next. The sample from step k to k + 1 is integrated with
``theta_at(k dt)``, so a change lands at an exact step in either clock mode. As a ROS parameter
or a reset's field it is one flat list, a row ``[t_start, t_end, theta_end...]`` of
2 + n_theta values per segment (van der Pol 0.5 -> -0.5 at 30 s: ``[30, 30, -0.5]``). Refuses
rows of the wrong length, segments out of order or overlapping, and a theta outside the
family's range (:meth:`~metampc_plant.family.ThetaComponent.support`). See docs/plant.md.
"""
from dataclasses import dataclass
import math
from typing import Sequence, Tuple

from metampc_plant.family import PlantFamily


@dataclass(frozen=True)
class Segment:
    """theta goes linearly to `theta_end` over [t_start, t_end] s of plant time (a step when
    equal)."""

    t_start: float
    t_end: float
    theta_end: Tuple[float, ...]


class ThetaSchedule:
    """theta(t) of one episode: the start value, then the segments in time order.

    Args:
        start: theta at t = 0, n_theta values.
        segments: in order, not overlapping (t_start >= the previous t_end).
    """

    def __init__(self, start: Sequence[float], segments: Sequence[Segment]):
        self.start = tuple(float(v) for v in start)
        self.segments = tuple(segments)
        # theta at each segment's start: the previous segment's end value (or the start).
        self._from = tuple([self.start] + [s.theta_end for s in self.segments[:-1]])

    @classmethod
    def parse(cls, flat: Sequence[float], family: PlantFamily, start: Sequence[float]
              ) -> 'ThetaSchedule':
        """The schedule of a flat row list (see the module docstring), checked.

        Raises:
            ValueError: naming the first row that does not fit: a length that is not a multiple
                of 2 + n_theta, a non-finite or negative time, t_end < t_start, a segment that
                starts before the previous one ends, a theta outside the family's range.
        """
        values = [float(v) for v in flat]
        width = 2 + family.n_theta
        if len(values) % width:
            names = ', '.join(c.name for c in family.theta)
            raise ValueError(f'theta_schedule of family {family.name} needs rows of {width} '
                             f'values [t_start, t_end, {names}], got {len(values)} values')
        segments, previous_end = [], 0.0
        for i in range(0, len(values), width):
            t_start, t_end, *theta = values[i:i + width]
            row = f'theta_schedule row {i // width} {values[i:i + width]}'
            if not all(math.isfinite(v) for v in values[i:i + width]):
                raise ValueError(f'{row}: values must be finite')
            if t_start < previous_end or t_end < t_start:
                raise ValueError(f'{row}: need {previous_end:g} <= t_start <= t_end (segments in '
                                 'time order, not overlapping)')
            try:
                family.check_theta_in_support(theta)
            except ValueError as err:
                raise ValueError(f'{row}: {err}') from None
            segments.append(Segment(t_start, t_end, tuple(theta)))
            previous_end = t_end
        return cls(family.check_theta(start), segments)

    def theta_at(self, t: float) -> Tuple[float, ...]:
        """theta at plant time t, s."""
        theta = self.start
        for segment, theta_from in zip(self.segments, self._from):
            if t < segment.t_start:
                break
            if t >= segment.t_end:
                theta = segment.theta_end
            else:
                w = (t - segment.t_start) / (segment.t_end - segment.t_start)
                theta = tuple(a + w * (b - a) for a, b in zip(theta_from, segment.theta_end))
        return theta

    def boundaries_passed(self, t: float) -> int:
        """How many segment starts and ends lie at or before plant time t: the plant
        re-announces its theta (latched plant_info) when this count moves, not on every step
        of a ramp (each output carries the exact theta)."""
        return sum((s.t_start <= t) + (s.t_end <= t) for s in self.segments)

    def flat(self) -> Tuple[float, ...]:
        """The rows again, as given to :meth:`parse`."""
        return tuple(v for s in self.segments for v in (s.t_start, s.t_end, *s.theta_end))


__all__ = ['Segment', 'ThetaSchedule']
