"""Stages 1 and 2 of the tuning (:mod:`.tuning`) as Optuna studies, asked and told by the
client while the trials run on the cluster (:mod:`.study_jobs`).

One study per method in one storage (:func:`open_storage`: a journal file or a database URL
shared by clients) over the method's grid. Stage 1: the given configurations, enqueued; stage
2: ``refine`` TPE trials, ``per_round`` asked at once per method. Each ask's sampler is seeded
from (seed, method, trial number), so the same seed gives the same trials and a stopped search
resumes with those of an uninterrupted one (asked, untold trials first). A configuration tried
already is never run twice (after :data:`DUPLICATE_ASKS`: a seeded draw among the untried).
With a :class:`.pruning.MedianRule` each trial carries its pruning thresholds (a user
attribute) and is told with its reports, COMPLETE or PRUNED. No rclpy, no torch here.
"""
import dataclasses
import itertools
import os
import re
from typing import Any, Dict, List, Optional, Sequence, Set, Tuple

import numpy as np
import optuna
from optuna.distributions import CategoricalDistribution
from optuna.trial import TrialState

from metampc_bringup.studies.pruning import MedianRule, REPORT_EVERY

SEED_STREAM = 0x79e      # sampler seeds: SeedSequence([seed, SEED_STREAM, method, number])
DUPLICATE_ASKS = 20      # asks for an untried configuration before a draw among them
TOLD = (TrialState.COMPLETE, TrialState.PRUNED)
THRESHOLDS = 'prune_above'   # the user attribute of a trial's pruning thresholds


def open_storage(where: str) -> optuna.storages.BaseStorage:
    """The Optuna storage at `where`: a database URL (``sqlite:///path``,
    ``postgresql://user@host/db``, anything with ``://``: Optuna's RDBStorage), else the path
    of a journal file (JournalFileBackend: appends, safe for several processes on one file
    system). ValueError naming `where` if Optuna cannot open it."""
    try:
        if '://' in where:
            return optuna.storages.RDBStorage(where)
        from optuna.storages.journal import JournalFileBackend, JournalStorage
        return JournalStorage(JournalFileBackend(os.path.abspath(where)))
    except Exception as err:    # a driver missing, a server not answering, a bad URL: say it
        raise ValueError(f'--storage {without_password(where)}: {err.__class__.__name__}: '
                         f'{str(err).splitlines()[0] if str(err) else ""}') from None


def without_password(url: str) -> str:
    """A storage URL as reports and errors show it: ``postgresql://user:***@host/db``."""
    return re.sub(r'^([a-z0-9+]+://[^:/@]*):[^@/]*@', r'\1:***@', url)


@dataclasses.dataclass(frozen=True)
class Trial:
    """A trial to evaluate, or evaluated: its study (method), number, configuration, stage
    ('search': stage 1, 'refine': stage 2) and pruning thresholds (None: not pruned)."""

    method: str
    number: int
    params: Dict[str, Any]
    stage: str
    prune_above: Optional[Tuple[float, ...]] = None


def _key(params: Dict[str, Any]) -> Tuple:
    return tuple(sorted(params.items()))


class Search:
    """The studies of a search in an Optuna storage (created, or resumed).

    Args:
        storage: where the studies are (:func:`open_storage`).
        spaces: per method, each parameter's values (the grid).
        first: per method, the stage-1 configurations (distinct, inside the grid).
        refine: stage-2 trials per method.
        per_round: stage-2 trials asked at once per method.
        seed: the search's seed.
        rule: the median pruner on the trials' reports (None: no pruning).
        tag: appended to the study names (``<method>-<tag>``): one search's studies in a
            storage that holds others.
    """

    def __init__(self, storage: str, spaces: Dict[str, Dict[str, Sequence[Any]]],
                 first: Dict[str, List[Dict[str, Any]]], refine: int, per_round: int,
                 seed: int, rule: Optional[MedianRule] = None, tag: str = ''):
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.spaces = spaces
        self.k = {m: len(first[m]) for m in spaces}
        self.refine, self.per_round, self.seed, self.rule = refine, per_round, seed, rule
        self._distributions = {m: {n: CategoricalDistribution(tuple(v)) for n, v in s.items()}
                               for m, s in spaces.items()}
        opened = open_storage(storage)
        self.names = {m: f'{m}-{tag}' if tag else m for m in spaces}
        self.studies = {}
        for method in spaces:
            study = optuna.create_study(
                storage=opened, study_name=self.names[method], direction='minimize',
                load_if_exists=True,
                pruner=rule.pruner() if rule else optuna.pruners.NopPruner())
            for params in first[method]:    # none again on resuming
                study.enqueue_trial(params, skip_if_exists=True)
            self.studies[method] = study

    def next_round(self) -> List[Trial]:
        """The trials to evaluate next, per method: those of an interrupted round, and new
        ones asked up to the round's end; none when every method's budget is told."""
        return [t for method in self.spaces for t in self._round(method)]

    def tell(self, method: str, number: int, value: float,
             reports: Sequence[float] = ()) -> None:
        """The score of a trial (NaN counts as inf: a failed run) and its reports."""
        self._report(method, number, reports)
        self.studies[method].tell(number, value if not np.isnan(value) else np.inf)

    def prune(self, method: str, number: int, reports: Sequence[float]) -> None:
        """A trial stopped by its pruner after `reports`: told PRUNED."""
        self._report(method, number, reports)
        self.studies[method].tell(number, state=TrialState.PRUNED)

    def _report(self, method: str, number: int, reports: Sequence[float]) -> None:
        """A trial's reports (at REPORT_EVERY, 2 REPORT_EVERY, ... steps) as its intermediate
        values. Optuna reports to a Trial object only, made here from the trial's id (none
        survives a resumed round)."""
        if not reports:
            return
        study = self.studies[method]
        trial_id, = [t._trial_id for t in study.get_trials(deepcopy=False)
                     if t.number == number]
        trial = optuna.trial.Trial(study, trial_id)
        for i, value in enumerate(reports):
            trial.report(value, (i + 1) * REPORT_EVERY)

    def completed(self) -> List[Trial]:
        """The told trials (COMPLETE or PRUNED, no duplicates), per method in the order
        asked."""
        out = []
        for method in self.spaces:
            told = self._told(method)
            out += [t for t in self._trials(method) if t.number in told]
        return out

    def best(self, method: str) -> Trial:
        """Optuna's best trial of the method's study."""
        best = self.studies[method].best_trial
        return next(t for t in self._trials(method) if t.number == best.number)

    def _told(self, method: str) -> Set[int]:
        return {t.number for t in self.studies[method].get_trials(deepcopy=False, states=TOLD)}

    def _trials(self, method: str) -> List[Trial]:
        """The method's asked trials that are not duplicates, in the order asked; a RUNNING
        duplicate (a stop between asking and telling it) is told failed here."""
        study = self.studies[method]
        out, seen = [], set()
        for t in sorted(study.get_trials(deepcopy=False), key=lambda t: t.number):
            if t.state not in (*TOLD, TrialState.RUNNING):
                continue
            if _key(t.params) in seen:
                study.tell(t.number, state=TrialState.FAIL)
                continue
            seen.add(_key(t.params))
            thresholds = t.user_attrs.get(THRESHOLDS)
            out.append(Trial(method, t.number, dict(t.params), self._stage(method, len(out)),
                             None if thresholds is None else tuple(thresholds)))
        return out

    def _stage(self, method: str, slot: int) -> str:
        return 'search' if slot < self.k[method] else 'refine'

    def _round_end(self, method: str, slot: int) -> int:
        """The end (exclusive) of the round of the trial slot `slot` (0: the first asked)."""
        k = self.k[method]
        if slot < k:
            return k
        return min(k + ((slot - k) // self.per_round + 1) * self.per_round, k + self.refine)

    def _round(self, method: str) -> List[Trial]:
        trials = self._trials(method)
        told = self._told(method)
        running = [t for t in trials if t.number not in told]
        slot = len(trials)
        if not running and slot >= self.k[method] + self.refine:
            return []
        end = self._round_end(method, slot - 1 if running else slot)
        tried = {_key(t.params) for t in trials}
        while slot < end:
            asked = self._ask_untried(method, tried)
            tried.add(_key(asked.params))
            thresholds = self.rule and self.rule.thresholds(self.studies[method])
            if thresholds is not None:
                asked.set_user_attr(THRESHOLDS, list(thresholds))
            running.append(Trial(method, asked.number, dict(asked.params),
                                 self._stage(method, slot), thresholds))
            slot += 1
        return running

    def _ask_untried(self, method: str, tried: Set[Tuple]) -> optuna.Trial:
        """A new trial of a configuration not in `tried` (the enqueued ones first)."""
        study, m = self.studies[method], list(self.spaces).index(method)
        for _ in range(DUPLICATE_ASKS):
            number = len(study.trials)
            seed = int(np.random.SeedSequence([self.seed, SEED_STREAM, m, number])
                       .generate_state(1)[0])
            study.sampler = optuna.samplers.TPESampler(
                seed=seed, n_startup_trials=self.k[method])
            trial = study.ask(self._distributions[method])
            if _key(trial.params) not in tried:
                return trial
            study.tell(trial, state=TrialState.FAIL)
        space = self.spaces[method]
        untried = [p for p in (dict(zip(space, values))
                               for values in itertools.product(*space.values()))
                   if _key(p) not in tried]
        rng = np.random.default_rng([self.seed, SEED_STREAM, m, len(study.trials)])
        study.enqueue_trial(untried[int(rng.integers(len(untried)))])
        return study.ask(self._distributions[method])
