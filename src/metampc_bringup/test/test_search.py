"""Stages 1-2 of the tuning as Optuna studies (metampc_bringup.studies.search), scored by a
made-up function of the configuration (no training here): the same seed asks the same trials,
a search stopped in the middle of a round resumes from its SQLite file with the trials an
uninterrupted one asks and evaluates only what is missing, no configuration runs twice, and
the best trial is the lowest score told."""
import math

import optuna

from metampc_bringup.studies.search import Search
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


def _search(path, seed=0, k=3, refine=4, per_round=2):
    return Search(str(path), SPACES, _first(k, seed), refine, per_round, seed)


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
               (('a.db', 0), ('b.db', 0), ('c.db', 1)))
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
    whole, evaluated_whole = _search(tmp_path / 'whole.db'), []
    _run(whole, evaluated_whole)
    path, evaluated = tmp_path / 'stopped.db', []
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
    search = _search(tmp_path / 's.db')
    _run(search, [])
    for method in SPACES:
        scores = {t.number: _score(method, t.params) for t in search.completed()
                  if t.method == method}
        assert search.best(method).number == min(scores, key=scores.get)
    # The storage is Optuna's: the dashboard and Optuna itself read the same trials.
    study = optuna.load_study(study_name='maml', storage=f'sqlite:///{tmp_path / "s.db"}')
    assert study.best_trial.number == search.best('maml').number
