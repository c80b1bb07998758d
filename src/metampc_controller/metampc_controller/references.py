"""Reference signals r(t) for the MPC's tracked outputs (y_bar of eq. (mpc)).

A reference is a signal of time put on the chosen output columns (default x1, column 0) of an
(N, n_y) array, the same value on each, or (set-point rows) one value per column; the other
columns are 0 (they carry weight 0 in the MPC). It is
evaluated over the horizon of the tick at time t0, i.e. at the samples t0 + dt, ..., t0 + N dt
that the MPC predicts (y_{t+1..t+N}). Kinds: 'setpoint', 'steps', 'sine', and
'setpoint_sequence' (set-points held for equal segments; by default the tracking task of the
paper's experiment: x1 set-points 0.8, -0.5, 0.3, -0.8 for 7.5 s each).
Times are in seconds, values in the units of the outputs.
"""
from abc import ABC, abstractmethod
from bisect import bisect_right
from dataclasses import dataclass, fields
from typing import Optional, Sequence, Union

import numpy as np

# Sample times t0 + k dt carry rounding error; a step due at 7.5 s must still apply to a sample
# computed as 7.4999999999999. 1 ns is far below any sample time.
_TIME_TOL = 1e-9


@dataclass(frozen=True, kw_only=True)
class ReferenceConfig:
    """What every reference has.

    Attributes:
        n_y: number of outputs of the plant/model.
        outputs: indices of the outputs that follow the signal (each gets the same signal).
    """

    n_y: int = 2
    outputs: Sequence[int] = (0,)

    def __post_init__(self):
        idx = np.asarray(self.outputs, dtype=int)
        if idx.ndim != 1 or idx.size == 0 or np.any(idx < 0) or np.any(idx >= self.n_y):
            raise ValueError(f'outputs must be indices in [0, {self.n_y}), got {self.outputs}')


@dataclass(frozen=True, kw_only=True)
class SetpointConfig(ReferenceConfig):
    """Constant value."""

    value: float = 0.0


@dataclass(frozen=True, kw_only=True)
class StepsConfig(ReferenceConfig):
    """Piecewise constant: each (time, value) holds from its time on; `initial` before the
    first. Times must be increasing."""

    steps: Sequence[Sequence[float]] = ()
    initial: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        times = [float(s[0]) for s in self.steps]
        if any(len(s) != 2 for s in self.steps) or np.any(np.diff(times) <= 0):
            raise ValueError(f'steps must be (time, value) pairs with increasing times, '
                             f'got {self.steps}')


@dataclass(frozen=True, kw_only=True)
class SineConfig(ReferenceConfig):
    """offset + amplitude sin(2 pi t / period + phase); period in s, phase in rad."""

    amplitude: float = 0.5
    period: float = 10.0
    offset: float = 0.0
    phase: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not self.period > 0:
            raise ValueError(f'period must be > 0, got {self.period}')


@dataclass(frozen=True, kw_only=True)
class SetpointSequenceConfig(ReferenceConfig):
    """Set-points held in turn (default: the paper's tracking task): each held `segment`
    seconds from `start` on, the first one before `start`, the last one after the end. A
    set-point is a number (every output follows it) or a row of one value per output of
    `outputs`, in their order (e.g. a tank's two levels, each one that the plant can hold)."""

    setpoints: Sequence[Union[float, Sequence[float]]] = (0.8, -0.5, 0.3, -0.8)
    segment: float = 7.5
    start: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not self.setpoints or not self.segment > 0:
            raise ValueError('need at least one set-point and segment > 0')
        ranks = {np.ndim(v) for v in self.setpoints}
        widths = {len(v) for v in self.setpoints} if ranks == {1} else set()
        if ranks != {0} and widths != {len(self.outputs)}:
            raise ValueError(f'set-points must be all numbers or all rows of '
                             f'{len(self.outputs)} values (one per output), got '
                             f'{[list(np.atleast_1d(v)) for v in self.setpoints]}')

    @property
    def duration(self) -> float:
        """Length of the task, s."""
        return len(self.setpoints) * self.segment


class Reference(ABC):
    """A signal on chosen outputs; evaluate() gives the MPC's (N, n_y) reference."""

    def __init__(self, config: ReferenceConfig):
        self.config = config
        self._outputs = np.asarray(config.outputs, dtype=int)
        # One output (the usual case) is a column, assigned without fancy indexing.
        self._column = int(self._outputs[0]) if len(set(config.outputs)) == 1 else None
        self._steps = np.arange(1, 1)   # 1..N of the last horizon, kept for the next tick

    @abstractmethod
    def signal(self, t: np.ndarray) -> np.ndarray:
        """Signal values (len(t),), or (len(t), n_outputs) for rows, at times t (s)."""

    def constant(self, t_first: float, t_last: float) -> Optional[float]:
        """The signal's value (a number, or a row (n_outputs,)) if it is the same at all times
        in [t_first, t_last] (as signal() computes it), else None (then evaluate() calls
        signal())."""
        return None

    def evaluate(self, t0: float, dt: float, N: int) -> np.ndarray:
        """References (N, n_y) at the samples t0 + dt, ..., t0 + N dt (computed as
        dt * k + t0: the same float64 operations whichever path below runs)."""
        out = np.zeros((N, self.config.n_y))
        columns = self._outputs if self._column is None else self._column
        value = self.constant(dt + t0, dt * N + t0)
        if value is not None:       # the whole horizon on one set-point (most ticks)
            out[:, columns] = value
            return out
        steps = self._steps
        if len(steps) != N:
            steps = self._steps = np.arange(1, N + 1)
        t = dt * steps
        t += t0
        signal = self.signal(t)
        if self._column is None and signal.ndim == 1:      # one value for every output
            signal = signal[:, None]
        out[:, columns] = signal
        return out


class Setpoint(Reference):
    """SetpointConfig.value at all times."""

    def signal(self, t: np.ndarray) -> np.ndarray:
        return np.full(len(t), float(self.config.value))

    def constant(self, t_first: float, t_last: float) -> Optional[float]:
        return float(self.config.value)


class Steps(Reference):
    """Piecewise constant signal of StepsConfig (right-continuous at the step times)."""

    def __init__(self, config: ReferenceConfig):
        super().__init__(config)
        self._times, self._values = self._table(config)
        self._time_list = self._times.tolist()     # for bisect on Python floats

    def constant(self, t_first: float, t_last: float) -> Optional[float]:
        # searchsorted(side='right') and bisect_right agree on float64 values; the sample
        # times grow with k, so one segment at both ends is one segment throughout.
        first = bisect_right(self._time_list, t_first + _TIME_TOL)
        if first != bisect_right(self._time_list, t_last + _TIME_TOL):
            return None
        return self._values[first]

    @staticmethod
    def _table(config: StepsConfig) -> tuple:
        """(step times (k,), values (k + 1,)) with values[0] before the first step."""
        times = np.array([s[0] for s in config.steps], dtype=float)
        values = np.array([config.initial] + [s[1] for s in config.steps], dtype=float)
        return times, values

    def signal(self, t: np.ndarray) -> np.ndarray:
        return self._values[self._times.searchsorted(t + _TIME_TOL, side='right')]


class Sine(Reference):
    """SineConfig's sinusoid."""

    def signal(self, t: np.ndarray) -> np.ndarray:
        c = self.config
        return c.offset + c.amplitude * np.sin(2.0 * np.pi * t / c.period + c.phase)


class SetpointSequence(Steps):
    """SetpointSequenceConfig's set-points as steps."""

    @staticmethod
    def _table(config: SetpointSequenceConfig) -> tuple:
        values = np.array([config.setpoints[0], *config.setpoints], dtype=float)
        if values.ndim == 2 and values.shape[1] == 1:   # rows of one output: numbers
            values = values[:, 0]
        times = config.start + config.segment * np.arange(len(config.setpoints))
        return times, values


KINDS = {'setpoint': (SetpointConfig, Setpoint), 'steps': (StepsConfig, Steps),
         'sine': (SineConfig, Sine),
         'setpoint_sequence': (SetpointSequenceConfig, SetpointSequence)}


def make_reference(kind: str, **params) -> Reference:
    """A reference of a kind ('setpoint', 'steps', 'sine', 'setpoint_sequence') from its config
    fields, e.g. make_reference('steps', steps=[(0.0, 0.5), (10.0, -0.5)], outputs=(0,))."""
    if kind not in KINDS:
        raise ValueError(f'unknown reference kind {kind!r}; kinds: {sorted(KINDS)}')
    config_cls, reference_cls = KINDS[kind]
    names = {f.name for f in fields(config_cls)}
    unknown = set(params) - names
    if unknown:
        raise ValueError(f'{kind}: unknown parameters {sorted(unknown)}; known: {sorted(names)}')
    return reference_cls(config_cls(**params))
