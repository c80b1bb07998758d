"""When to ask the learner for a model adapted to the latest samples (adaptation in the loop).

Pure Python (no rclpy). The controller measures how well its model predicts the plant
(:mod:`~metampc_controller.prediction_error`) and asks the learner to adapt, on the samples up
to the step of the request, by one of two rules:

* ``periodic``: at every ``adapt_period`` s of the episode's plant time (t = k dt).
* ``triggered``: a CUSUM on the T-step prediction error e_k against the error of the model
  right after it came into use. Once a model is in use, the median of its errors over the
  first ``baseline_s`` s is its baseline b; then
  ``s_k = max(0, s_{k-1} + log(e_k / b) - cusum_drift)`` and a request goes out when
  ``s_k > cusum_threshold``. The log makes it scale-free (the same settings for every family
  and model); the drift is the allowance (0.7 ~ log 2: errors below about twice the baseline
  never accumulate); the threshold how much excess evidence a request needs (5: e.g. 5 steps
  at 5.4 times the baseline, or 20 steps at 2.6 times).

Hysteresis, so that the requests do not chatter: one request at a time; after it, nothing is
asked until the answering model is in use and its own baseline is measured (``baseline_s``),
and a request the learner never answers is given up after ``adapt_timeout`` s of wall time
(the node's timer) with the model in use kept.

Swap: under a lockstep plant the answer to step ``request + swap_delay`` waits for the
requested model (the plant waits with it), so a seeded run swaps at the same step whatever the
machine; in real time the model is used from the tick after it was built, and nothing waits.
A reset of the plant (a new episode) forgets the baseline, the statistic and the request.
The settings are live parameters of the controller (an experiment switches the mode between
its runs); a change applies from the next tick, the periods from the next episode.
"""
from dataclasses import dataclass
import math
from typing import List, Optional

import numpy as np

from metampc_common.params import check_fields, param

MODES = ('off', 'periodic', 'triggered')


@dataclass
class TriggerConfig:
    """The adaptation-in-the-loop settings of the controller (see the module docstring)."""

    adaptation: str = param('off', 'adaptation in the loop: off, periodic (every adapt_period '
                                   's) or triggered (CUSUM on the prediction error)',
                            choices=MODES, live=True)
    adapt_period: float = param(10.0, 'periodic: plant time between requests, s', gt=0,
                                live=True)
    cusum_drift: float = param(0.7, 'triggered: allowance per step on log(error / baseline) '
                                    '(0.7 ~ log 2: errors below about twice the baseline '
                                    'never accumulate)', ge=0, live=True)
    cusum_threshold: float = param(5.0, 'triggered: CUSUM level that sends a request', gt=0,
                                   live=True)
    baseline_s: float = param(3.0, 'triggered: plant time after a model comes into use whose '
                                   'median T-step error is its baseline, s', gt=0, live=True)
    swap_delay: int = param(10, 'lockstep: the answer of step request + swap_delay waits for '
                                'the requested model (realtime: used on arrival)', ge=1,
                        live=True)
    adapt_timeout: float = param(60.0, 'wall time to wait for a requested model before going '
                                       'on with the model in use, s', gt=0, live=True)

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)


@dataclass
class Request:
    """A request for adaptation: made at `step` (the samples up to it), by `trigger`
    ('periodic' or 'triggered'), with the model `version` in use; the answer to
    `swap_step` waits for it under a lockstep plant."""

    step: int
    swap_step: int
    trigger: str
    version: int


class AdaptationTrigger:
    """The request rule of one controller (module docstring); fed once per tick."""

    def __init__(self, config: TriggerConfig):
        self.config = config
        self.pending: Optional[Request] = None
        self.statistic = 0.0            # CUSUM s_k (0 while no baseline)
        self.baseline = math.nan        # b of the model in use (NaN while measuring)
        self._version = 0               # model whose baseline is measured or known
        self._since: Optional[int] = None   # first step of that model's baseline window
        self._errors: List[float] = []
        self._next_period = config.adapt_period

    def new_episode(self) -> None:
        """A plant reset: forget the baseline, the statistic and any request."""
        self.pending = None
        self._restart(self._version)
        self._next_period = self.config.adapt_period

    def _restart(self, version: int) -> None:
        self._version, self._since, self._errors = version, None, []
        self.baseline, self.statistic = math.nan, 0.0

    def answered(self, version: int) -> None:
        """The requested model (`version`) is in use: the request is done."""
        self.pending = None
        self._restart(version)

    def give_up(self) -> None:
        """The request was not answered in time: keep the model in use, ask again later."""
        self.pending = None
        self._restart(self._version)

    def update(self, step: int, dt: float, error_t: float, version: int) -> Optional[Request]:
        """The tick of `step` (plant time step x dt) measured `error_t` (NaN: none yet) with
        model `version` (0: none); returns the request it makes, if any."""
        cfg = self.config
        if cfg.adaptation == 'off' or version == 0 or self.pending is not None:
            return None
        if version != self._version:
            self._restart(version)
        if cfg.adaptation == 'periodic':
            if step * dt + 1e-9 < self._next_period:
                return None
            while self._next_period <= step * dt + 1e-9:
                self._next_period += cfg.adapt_period
            return self._request(step, 'periodic', version)
        if not math.isfinite(error_t) or error_t <= 0:
            return None
        if math.isnan(self.baseline):
            if self._since is None:
                self._since = step
            self._errors.append(error_t)
            if (step - self._since + 1) * dt >= cfg.baseline_s - 1e-9:
                self.baseline = float(np.median(self._errors))
            return None
        self.statistic = max(0.0, self.statistic + math.log(error_t / self.baseline)
                             - cfg.cusum_drift)
        if self.statistic > cfg.cusum_threshold:
            return self._request(step, 'triggered', version)
        return None

    def _request(self, step: int, trigger: str, version: int) -> Request:
        self.pending = Request(step, step + self.config.swap_delay, trigger, version)
        return self.pending

    def waits(self, step: int) -> bool:
        """Lockstep: True if the answer of `step` must wait for the requested model."""
        return self.pending is not None and step >= self.pending.swap_step


__all__ = ['MODES', 'TriggerConfig', 'Request', 'AdaptationTrigger']
