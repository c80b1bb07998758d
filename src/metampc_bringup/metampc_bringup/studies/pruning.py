"""Optuna's median pruner on the meta-training loss, decided where the trial runs.

A trial runs on a worker without a line back to its study, so the client hands each trial,
when it asks it, the thresholds of Optuna's ``MedianPruner`` at every step the trial will
report: the median over the study's COMPLETE trials of their reports at that step
(:func:`thresholds`). The worker's meta-training reports every :data:`REPORT_EVERY` outer
steps the mean of the last :data:`REPORT_EVERY` losses (:func:`reports`) and stops at the
first step where its best report so far is above the step's threshold, or NaN
(:func:`pruned_at`): MedianPruner's rule, checked against Optuna's own pruner in
test_search. The thresholds come from the trials told before the trial was asked, so which
trials are pruned does not depend on timing: the same search, stopped and resumed or not,
prunes the same ones. The same rule for every method (the fairness rule). No torch here.
"""
import dataclasses
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np
import optuna
from optuna.trial import TrialState

REPORT_EVERY = 10        # outer steps between reports (each the mean of as many losses)
OFF = math.nan           # a threshold that never prunes (start-up, warm-up)
NO_MEDIAN = math.inf     # no COMPLETE trial reported there: only a NaN report prunes


@dataclasses.dataclass(frozen=True)
class MedianRule:
    """MedianPruner(n_startup_trials=startup_trials, n_warmup_steps=warmup_steps) over the
    reports at `steps` (the outer steps a trial of `iterations` reports at)."""

    iterations: int
    startup_trials: int = 5
    warmup_steps: int = 0

    @property
    def steps(self) -> Tuple[int, ...]:
        return tuple(range(REPORT_EVERY, self.iterations + 1, REPORT_EVERY))

    def pruner(self) -> optuna.pruners.MedianPruner:
        """Optuna's pruner of this rule (the study's, for optuna-dashboard and the check)."""
        return optuna.pruners.MedianPruner(n_startup_trials=self.startup_trials,
                                           n_warmup_steps=self.warmup_steps)

    def thresholds(self, study: optuna.Study) -> Optional[Tuple[float, ...]]:
        """Per report step, the threshold of a trial asked now (:data:`OFF`, :data:`NO_MEDIAN`
        or the median of the COMPLETE trials' reports there); None if all are OFF."""
        done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        out = []
        for step in self.steps:
            if not done or len(done) < self.startup_trials or step < self.warmup_steps:
                out.append(OFF)
                continue
            values = [t.intermediate_values[step] for t in done
                      if step in t.intermediate_values]
            out.append(float(np.nanpercentile(np.array(values, float), 50)) if values
                       else NO_MEDIAN)
        return None if all(math.isnan(v) for v in out) else tuple(out)


def reports(losses: Sequence[float]) -> List[float]:
    """The reports of a meta-training's per-step losses so far: at every
    :data:`REPORT_EVERY`-th step, the mean of the finite ones of the last REPORT_EVERY (NaN
    if none is)."""
    out = []
    for end in range(REPORT_EVERY, len(losses) + 1, REPORT_EVERY):
        window = np.asarray(losses[end - REPORT_EVERY:end], float)
        finite = window[np.isfinite(window)]
        out.append(float(finite.mean()) if finite.size else math.nan)
    return out


def pruned_at(given: Sequence[float], thresholds: Sequence[float]) -> Optional[int]:
    """The report step (REPORT_EVERY, 2 REPORT_EVERY, ...) at which MedianPruner prunes the
    trial whose reports so far are `given`; None if at none of them."""
    for i, threshold in enumerate(thresholds[:len(given)]):
        if math.isnan(threshold):
            continue
        best = np.asarray(given[:i + 1], float)
        best = best[~np.isnan(best)]
        if not best.size or best.min() > threshold:
            return (i + 1) * REPORT_EVERY
    return None
