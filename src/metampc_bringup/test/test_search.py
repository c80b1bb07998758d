"""Stages 1-2 of the tuning as Optuna studies (metampc_bringup.studies.search), scored by a
made-up function of the configuration (no training here): the same seed asks the same trials,
a search stopped in the middle of a round resumes from its journal file with the trials an
uninterrupted one asks and evaluates only what is missing, no configuration runs twice, the
best trial is the lowest score told, two clients of one database see one search, and the
median pruner stops a trial where Optuna's own would."""
import copy
import math

import optuna
from optuna.trial import TrialState
import pytest

from metampc_bringup.studies.pruning import MedianRule, pruned_at, REPORT_EVERY
from metampc_bringup.studies.search import open_storage, Search
from metampc_bringup.studies.tuning import AXES, draw_jobs, searched

SPACES = {m: AXES[m] for m in ('imaml', 'maml')}


def _first(k: int, seed: int):
    drawn = draw_jobs(k, 10, seed)
    return {m: [searched(j) for j in drawn if j.method == m] for m in SPACES}


def _score(method: str, params: dict) -> float:
    """Lowest at M 20, lr_inner 0.1, lr_outer 5e-3 (gamma 1 for iMAML); inf at M 5 and lr_inner
    0.2, a failed run."""
    if params['inner_steps'] == 5 and params['lr_inner'] == 0.2:
        return math.inf
    return (abs(math.log(params['inner_steps'] / 20)) + abs(math.log(params['lr_inner'] / 0.1))
            + abs(math.log(params['lr_outer'] / 5e-3))
            + abs(math.log(params.get('gamma', 1.0))) + (method == 'maml'))


def _search(path, seed=0, k=3, refine=4, per_round=2, **kwargs):
    return Search(str(path), SPACES, _first(k, seed), refine, per_round, seed, **kwargs)


def _run(search, evaluated, stop_after=None):
    """Evaluate rounds until done; with `stop_after` (rounds), tell only the first trial of
    the last round and return (a stop)."""
    rounds = 0
    while True:
        trials = search.next_round()
        if not trials:
            return
        rounds += 1
        for t in trials:
            evaluated.append((t.method, t.number))
            search.tell(t.method, t.number, _score(t.method, t.params))
            if rounds == stop_after:
                return


def _record(search):
    return [(t.method, t.number, t.params, t.stage) for t in search.completed()]


def test_the_same_seed_asks_the_same_trials_and_stage_1_is_the_draws(tmp_path):
    a, b, c = (_search(tmp_path / name, seed) for name, seed in
               (('a.journal', 0), ('b.journal', 0), ('c.journal', 1)))
    for search in (a, b, c):
        _run(search, [])
    assert _record(a) == _record(b)
    assert [r[2] for r in _record(a)] != [r[2] for r in _record(c)]
    for method in SPACES:
        mine = [r for r in _record(a) if r[0] == method]
        assert len(mine) == 3 + 4 and [r[3] for r in mine] == ['search'] * 3 + ['refine'] * 4
        assert [r[2] for r in mine[:3]] == _first(3, 0)[method]     # calibration first
        assert len({tuple(sorted(r[2].items())) for r in mine}) == 7  # never the same twice


def test_a_stopped_search_resumes_from_its_file_with_only_the_missing_trials(tmp_path):
    whole, evaluated_whole = _search(tmp_path / 'whole.journal'), []
    _run(whole, evaluated_whole)
    path, evaluated = tmp_path / 'stopped.journal', []
    _run(_search(path), evaluated, stop_after=2)   # stage 1, then one trial of a stage-2 round
    stopped = len(evaluated)
    assert stopped == 2 * 3 + 1
    resumed = _search(path)     # what the same command does: opens the file again
    first_round = resumed.next_round()
    # The round's asked and untold trials first (the same numbers), topped up to its size.
    assert [(t.method, t.number) for t in first_round] == [
        mt for mt in evaluated_whole[stopped:] if mt not in evaluated][:len(first_round)]
    for t in first_round:
        evaluated.append((t.method, t.number))
        resumed.tell(t.method, t.number, _score(t.method, t.params))
    _run(resumed, evaluated)
    assert _record(resumed) == _record(whole)
    assert sorted(evaluated) == sorted(evaluated_whole)     # each trial evaluated once


def test_the_best_trial_is_the_lowest_score_told(tmp_path):
    search = _search(tmp_path / 's.journal')
    _run(search, [])
    for method in SPACES:
        scores = {t.number: _score(method, t.params) for t in search.completed()
                  if t.method == method}
        assert search.best(method).number == min(scores, key=scores.get)
    # The storage is Optuna's: the dashboard and Optuna itself read the same trials.
    study = optuna.load_study(study_name='maml',
                              storage=open_storage(str(tmp_path / 's.journal')))
    assert study.best_trial.number == search.best('maml').number


@pytest.mark.parametrize('kind', ['sqlite', 'journal'])
def test_two_clients_of_one_storage_see_one_search(tmp_path, kind):
    """--storage: a search stopped by one client (a Search on a database URL or a journal
    file) is seen whole by a second one opened on the same storage and tag (the same command
    on another machine), which asks the stopped round's trials the first would; a search of
    another tag in that storage is apart."""
    where = (f'sqlite:///{tmp_path / "shared.db"}' if kind == 'sqlite'
             else str(tmp_path / 'shared.journal'))
    first = _search(where, tag='abc')
    _run(first, [], stop_after=2)
    second = _search(where, tag='abc')
    assert _record(second) == _record(first) and len(_record(first)) == 2 * 3 + 1
    asked = [(t.method, t.number, t.params) for t in second.next_round()]
    assert asked and asked == [(t.method, t.number, t.params) for t in first.next_round()]
    other = _search(where, tag='xyz')
    assert _record(other) == []
    assert sorted(optuna.get_all_study_names(open_storage(where))) == [
        'imaml-abc', 'imaml-xyz', 'maml-abc', 'maml-xyz']


STEPS = 5       # reports per trial: outer steps 10, 20, ..., 50


def _reports(method: str, params: dict) -> list:
    """Made-up meta-training reports: a configuration's score plus a decaying term, and for
    lr_inner 0.05 a bump at the fourth (not monotonic: the rule takes the trial's best so
    far); NaN from the third report on for a failed run's configuration."""
    base = _score(method, params)
    bump = 3.0 if params['lr_inner'] == 0.05 else 0.0
    return [math.nan if math.isinf(base) and i >= 2
            else min(base, 9.0) + 1.0 / (i + 1) + bump * (i == 3) for i in range(STEPS)]


def test_the_median_pruner_stops_a_trial_where_optunas_would(tmp_path):
    """Stage-2 trials are asked with thresholds; the worker's rule (pruned_at) stops each at
    the step where Optuna's MedianPruner, on the study as the trial was asked, prunes it given
    the same reports, and runs the others to their end; the pruned are told PRUNED with
    their reports up to there, count in the budget and never come back."""
    rule = MedianRule(STEPS * REPORT_EVERY, startup_trials=3, warmup_steps=2 * REPORT_EVERY)
    search = _search(tmp_path / 'p.journal', rule=rule, refine=6)
    pruned, ran = [], []
    while trials := search.next_round():
        decided = []
        for t in trials:
            given = _reports(t.method, t.params)
            study = search.studies[t.method]
            step = None if t.prune_above is None else pruned_at(given, t.prune_above)
            frozen = copy.deepcopy(next(f for f in study.get_trials() if f.number == t.number))
            optunas = None
            for i in range(STEPS):
                frozen.intermediate_values = {(j + 1) * REPORT_EVERY: given[j]
                                              for j in range(i + 1)}
                if study.pruner.prune(study, frozen):
                    optunas = (i + 1) * REPORT_EVERY
                    break
            assert step == optunas, (t, given, t.prune_above)
            assert t.prune_above is None or t.stage == 'refine'
            decided.append((t, given, step))
        for t, given, step in decided:      # told after the round, as run_jobs does
            if step:
                search.prune(t.method, t.number, given[:step // REPORT_EVERY])
                pruned.append((t.method, t.number))
            else:
                search.tell(t.method, t.number, _score(t.method, t.params), given)
                ran.append((t.method, t.number))
    assert pruned and any(m == 'maml' for m, _ in ran if (m, _) not in pruned)
    for method in SPACES:
        study = search.studies[method]
        states = {t.number: t.state for t in study.get_trials()}
        mine = [t for t in search.completed() if t.method == method]
        assert len(mine) == 3 + 6       # pruned trials count in the budget
        assert {t.number for t in mine if states[t.number] == TrialState.PRUNED} == \
            {n for m, n in pruned if m == method}
        assert len({tuple(sorted(t.params.items())) for t in mine}) == len(mine)
        assert search.best(method).number not in {n for m, n in pruned if m == method}
        for t in study.get_trials(states=(TrialState.PRUNED,)):
            assert len(t.intermediate_values) < STEPS
