"""When to ask the learner for a model adapted to the latest samples (adaptation in the loop).

Pure Python (no rclpy). Three rules, fed once per tick: ``periodic`` (every ``adapt_period`` s
of the episode's plant time); ``triggered``, a CUSUM on the NSSM's relative T-step error e_k =
E_k / (D_k + error_floor) (:mod:`~metampc_controller.prediction_error`) against its median b
over the model's first ``baseline_s`` s: s_k = max(0, s_{k-1} + log(e_k / b) - cusum_drift), a
request when s_k > cusum_threshold; ``posterior``, a feature NARX under the in-loop RLS: the
windowed chi-square test of its normalised innovations (:mod:`.innovation_test`). Hysteresis:
one request at a time, then nothing until the answering model is in use (and its baseline
measured); a request never answered is given up after ``adapt_timeout`` s of wall time. A plant
reset forgets baseline, statistic and request. Live parameters. Why: docs/adaptation.md.
"""
from dataclasses import dataclass
import math
from typing import List, Optional

import numpy as np

from metampc_common.params import check_fields, param
from metampc_controller.innovation_test import InnovationTest

MODES = ('off', 'periodic', 'triggered', 'posterior')


@dataclass
class TriggerConfig:
    """The adaptation-in-the-loop settings of the controller (see the module docstring)."""

    adaptation: str = param('off', 'adaptation in the loop: off, periodic (every adapt_period '
                                   's), triggered (CUSUM on the prediction error) or posterior '
                                   "(a feature NARX under the in-loop RLS: its posterior's "
                                   'innovations fail a chi-square test)',
                            choices=MODES, live=True)
    adapt_period: float = param(10.0, 'periodic: plant time between requests, s', gt=0,
                                live=True)
    cusum_drift: float = param(
        1.5, 'triggered: allowance per step on log(error / baseline) (1.5: errors below 4.5 '
             'times the baseline never accumulate)', ge=0, live=True)
    cusum_threshold: float = param(10.0, 'triggered: CUSUM level that sends a request', gt=0,
                                   live=True)
    baseline_s: float = param(7.5, 'triggered: plant time after a model comes into use whose '
                                   'median relative error is its baseline, s', gt=0, live=True)
    error_floor: float = param(0.01, 'triggered: added to the outputs\' T-step change in the '
                                     'relative error (normalised units: a change of 0.1 std '
                                     'counts as motion)', gt=0, live=True)
    posterior_window: int = param(20, 'posterior: ticks of normalised innovations summed in '
                                      'the chi-square test', ge=1, live=True)
    posterior_alpha: float = param(1e-6, 'posterior: false-alarm probability per tick of the '
                                         'chi-square test (its tail at the threshold)', gt=0,
                                   lt=1, live=True)
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
    ('periodic', 'triggered' or 'posterior'), with the model `version` in use; the answer to
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
        self._test: Optional[InnovationTest] = None     # posterior's, built at its first use

    def new_episode(self) -> None:
        """A plant reset: forget the baseline, the statistic and any request."""
        self.pending = None
        self._restart(self._version)
        self._next_period = self.config.adapt_period

    def _restart(self, version: int) -> None:
        self._version, self._since, self._errors = version, None, []
        self.baseline, self.statistic = math.nan, 0.0
        if self._test is not None:
            self._test.clear()

    def answered(self, version: int) -> None:
        """The requested model (`version`) is in use: the request is done."""
        self.pending = None
        self._restart(version)

    def give_up(self) -> None:
        """The request was not answered in time: keep the model in use, ask again later."""
        self.pending = None
        self._restart(self._version)

    def update(self, step: int, dt: float, error_t: float, change_t: float, version: int,
               innovation: Optional[np.ndarray] = None) -> Optional[Request]:
        """The tick of `step` (plant time step x dt) measured the T-step error `error_t` and
        output change `change_t` (NaN: none yet) with model `version` (0: none), and the RLS
        posterior's normalised innovation (n_y,) (None: no RLS; NaN: none this tick); returns
        the request it makes, if any."""
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
        if cfg.adaptation == 'posterior':
            return self._posterior(step, version, innovation)
        if not (math.isfinite(error_t) and math.isfinite(change_t)) or error_t <= 0:
            return None
        error_t = error_t / (change_t + cfg.error_floor)
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

    def _posterior(self, step: int, version: int, innovation: Optional[np.ndarray]
                   ) -> Optional[Request]:
        """The posterior rule: statistic the window's sum, baseline the test's threshold."""
        if innovation is None:
            return None
        cfg, test = self.config, self._test
        key = (cfg.posterior_window, len(innovation))
        if test is None or (test.window, test.n_y) != key or test.alpha != cfg.posterior_alpha:
            test = self._test = InnovationTest(cfg.posterior_window, cfg.posterior_alpha,
                                               len(innovation))
        rejects = test.update(innovation)
        self.statistic, self.baseline = test.statistic, test.threshold
        return self._request(step, 'posterior', version) if rejects else None

    def _request(self, step: int, trigger: str, version: int) -> Request:
        self.pending = Request(step, step + self.config.swap_delay, trigger, version)
        return self.pending

    def waits(self, step: int) -> bool:
        """Lockstep: True if the answer of `step` must wait for the requested model."""
        return self.pending is not None and step >= self.pending.swap_step


__all__ = ['MODES', 'TriggerConfig', 'Request', 'AdaptationTrigger']
