"""The search's bookkeeping (metampc_bringup.studies.tuning): draws, stages, scores.

Pure functions on job lists and hand-made results; no training runs here (scripts/tune.py
runs them, docs/tuning.md has the measured search).
"""
import importlib.util
import json
import math
import os
from pathlib import Path
import re

import optuna
import pytest

from metampc_bringup.experiment_config import load

from metampc_bringup.studies import tuning
from metampc_bringup.studies.learning_setup import Job, settings_from
from metampc_bringup.studies.search import open_storage
from metampc_bringup.studies.tuning import (ADAPT_LRS, best_of, CALIBRATION, CG_STEPS, CURVATURE,
                                            draw_jobs, GAMMA_GRID, request_fields, robust_jobs,
                                            robust_scores, SHARED_GRID, TuneConfig)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))


def _result(method, index, hyper, score, lrs=None):
    return {'method': method, 'index': index, 'hyper': hyper, 'score': score,
            'adapt': [{'lr': lr, 'score': s} for lr, s in (lrs or {}).items()]}


def test_draws_are_paired_seeded_and_start_at_the_calibration():
    jobs = draw_jobs(8, 150, seed=0)
    imaml = [j for j in jobs if j.method == 'imaml']
    maml = [j for j in jobs if j.method == 'maml']
    assert len(imaml) == len(maml) == 8
    assert [j.method for j in jobs].count('supervised') == 1
    shared = tuple(SHARED_GRID)
    for a, b in zip(imaml, maml):
        assert a.index == b.index
        assert {n: a.hyper[n] for n in shared} == b.hyper     # the same draw for both
    assert maml[0].hyper == {n: CALIBRATION[n] for n in shared}
    assert imaml[0].hyper['gamma'] == CALIBRATION['gamma']
    # 7 further gammas cycle through the grid: each of the 6 at least once
    assert set(j.hyper['gamma'] for j in imaml[1:]) == set(GAMMA_GRID)
    assert len({tuple(sorted(j.hyper.items())) for j in maml}) == 8   # no repeats
    assert [j.hyper for j in draw_jobs(8, 150, seed=0)] == [j.hyper for j in jobs]
    assert [j.hyper for j in draw_jobs(8, 150, seed=1)] != [j.hyper for j in jobs]


def test_imaml_gets_the_cg_steps_of_its_gamma():
    for job in draw_jobs(8, 150, seed=3):
        if job.method == 'imaml':
            assert job.hyper['cg_steps'] == CG_STEPS[job.hyper['gamma']]
        else:
            assert 'cg_steps' not in job.hyper and 'gamma' not in job.hyper
    # more steps for a smaller gamma (worse conditioned I + G/gamma), never fewer
    steps = [CG_STEPS[g] for g in sorted(GAMMA_GRID)]
    assert steps == sorted(steps, reverse=True)


def test_robust_stage_and_scores():
    results = [_result('imaml', i, {'gamma': 1.0}, s) for i, s in enumerate([0.3, 0.1, 0.2])]
    results.append(_result('imaml', 3, {'gamma': 3.0}, math.inf))
    jobs = robust_jobs(results, 2, 300, [1000, 1001])
    assert [(j.index, j.source_seed) for j in jobs] == [(1, 1000), (1, 1001), (2, 1000),
                                                        (2, 1001)]
    runs = [{**_result('imaml', 1, {'gamma': 1.0}, 0, {0.1: 1.0, 0.2: 4.0}), 'source_seed': 1000},
            {**_result('imaml', 1, {'gamma': 1.0}, 0, {0.1: 3.0, 0.2: 0.5}), 'source_seed': 1001}]
    (score,) = robust_scores(runs)
    # means per step size: 0.1 -> 2.0, 0.2 -> 2.25; the best step size is 0.1
    assert score['best_lr'] == 0.1 and score['score'] == pytest.approx(2.0)
    assert score['score_per_seed'] == [1.0, 3.0] and score['source_seeds'] == [1000, 1001]
    failed = [{'method': 'maml', 'index': 0, 'hyper': {}, 'adapt': [], 'source_seed': 1000}]
    assert robust_scores(failed)[0]['score'] == math.inf


def test_winner_fields_are_request_fields():
    best = best_of('imaml', [_result('imaml', 0, {'gamma': 0.1, 'cg_steps': 10}, 0.2),
                             _result('imaml', 1, {'gamma': 3.0, 'cg_steps': 5}, 0.1)])
    best['best_lr'] = 0.3
    fields = request_fields(best, 300, 16, 20)
    assert fields['meta_train'] == {'iterations': 300, 'batch_size': 16, 'gamma': 3.0,
                                    'cg_steps': 5}
    assert fields['adapt'] == {'steps': 20, 'lr': 0.3}
    sup = request_fields({'method': 'supervised', 'index': 0, 'score': 1.0, 'best_lr': 0.5},
                         300, 16, 20)
    assert 'meta_train' not in sup


@pytest.mark.parametrize('name, value', [('k', 0), ('per_round', 0), ('refine', -1),
                                         ('robust_seeds', 0), ('k', 45)])
def test_bad_settings_are_refused(name, value):
    with pytest.raises(ValueError, match=name):
        TuneConfig(**{name: value}).validate()


def test_k_beyond_the_grid_is_refused():
    size = math.prod(len(v) for v in SHARED_GRID.values())
    with pytest.raises(ValueError, match='exceeds the grid'):
        tuning.draw_jobs(size + 1, 10, 0)


def test_the_incumbent_joins_the_robust_stage_once():
    results = [_result('maml', i, {'inner_steps': 5, 'lr_inner': 0.02, 'lr_outer': lr}, s)
               for i, (lr, s) in enumerate([(1e-2, 0.1), (5e-3, 0.2), (2e-3, 0.3)])]
    used = {'inner_steps': 5, 'lr_inner': 0.05, 'lr_outer': 1e-3}
    jobs = robust_jobs(results, 2, 300, [1000], {'maml': used})
    expected = [(0, results[0]['hyper']), (1, results[1]['hyper']), (tuning.INCUMBENT, used)]
    assert [(j.index, j.hyper) for j in jobs] == expected
    # an incumbent that is a finalist already is not run twice
    again = robust_jobs(results, 2, 300, [1000], {'maml': results[1]['hyper']})
    assert [j.index for j in again] == [0, 1]


def test_incumbents_are_the_experiments_requests():
    path = os.path.join(ROOT, 'config', 'default.yaml')
    got = tuning.incumbents(path)
    requests = load(path).meta_train
    for method in ('imaml', 'maml'):
        assert set(got[method]) >= set(tuning.AXES[method])
        assert all(requests[method][n] == v for n, v in got[method].items())
    assert got['imaml']['cg_steps'] == requests['imaml']['cg_steps']


def _script():
    spec = importlib.util.spec_from_file_location(
        'tune', Path(__file__).resolve().parents[3] / 'scripts' / 'tune.py')
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


@pytest.mark.parametrize('args', [['--out', 'EXISTING'], ['--out', 'NEW', '--k', '0'],
                                  ['--out', 'NEW', '--jobs', '0'],
                                  ['--out', 'NEW', '--scheduler', 'tcp://10.0.0.5:8786'],
                                  ['--out', 'NEW', '--storage',
                                   'mysql://nobody:hunter2@127.0.0.1:1/x']])
def test_script_refuses_bad_arguments_and_an_existing_out_with_one_line(tmp_path, capsys, args):
    """scripts/tune.py: exit 2, one line, nothing written (config/tuning.json, the committed
    record, was its old default --out and got overwritten without a word); a storage URL's
    password is not shown."""
    script = _script()
    existing = tmp_path / 'tuning.json'
    existing.write_text('{"an": "earlier record"}')
    paths = {'EXISTING': str(existing), 'NEW': str(tmp_path / 'new.json')}
    assert script.main([paths.get(a, a) for a in args]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'hunter2' not in err, err
    assert existing.read_text() == '{"an": "earlier record"}'
    assert not (tmp_path / 'new.json').exists() and not (tmp_path / 'new.study').exists()


TINY_SEARCH = ['--k', '2', '--refine', '2', '--per-round', '1', '--iterations', '2',
               '--batch-size', '2', '--finalists', '0', '--thetas', '1', '--adapt-steps', '2',
               '--score', 'prediction']


def test_tune_on_two_workers_reports_optunas_best_and_the_same_command_resumes(
        tmp_path, capsys, tiny_config, direct, untimed):
    """Its configurations are those of direct calls (the process pool's before); each
    method's winner is its study's best trial; the same command again runs nothing, and
    with another seed it is refused."""
    out = tmp_path / 'tuning.json'
    args = ['--config', str(tiny_config), *TINY_SEARCH, '--jobs', '2', '--out', str(out)]
    assert _script().main(args) == 0
    report = json.loads(out.read_text())
    folder = tmp_path / 'tuning.study'
    assert report['protocol']['per_round'] == 1 and report['jobs'] == 2
    stages = [(r['method'], r['stage']) for r in report['configurations']]
    assert stages == [(m, s) for m in ('imaml', 'maml') for s in ('search',) * 2 + ('refine',) * 2
                      ] + [('supervised', 'search')]
    assert report['study']['storage'] == str(folder / 'study.journal')
    for method in ('imaml', 'maml'):
        best = optuna.load_study(study_name=report['study']['names'][method],
                                 storage=open_storage(str(folder / 'study.journal'))).best_trial
        winner = report['winners'][method]
        assert (winner['index'], winner['score']) == (best.number, best.value)
        assert {n: winner['meta_train'][n] for n in best.params} == best.params
    settings = settings_from(str(tiny_config), 1, 2, {'batch_size': 2, 'curvature': CURVATURE})
    jobs = [Job(r['method'], r['index'], r['hyper'], r['iterations'], ADAPT_LRS, r['stage'])
            for r in report['configurations']]
    assert [untimed(r) for r in report['configurations']] == [
        direct(settings, job) for job in jobs]

    cached = {p: p.stat().st_mtime_ns for p in (folder / 'cache').iterdir()}
    out.unlink()
    assert _script().main(args) == 0
    assert {p: p.stat().st_mtime_ns for p in (folder / 'cache').iterdir()} == cached
    assert json.loads(out.read_text())['configurations'] == report['configurations']
    out.unlink()
    capsys.readouterr()
    assert _script().main([*args[:-2], '--seed', '1', '--out', str(out)]) == 2
    assert 'holds a search with other settings (seed)' in capsys.readouterr().err


def test_control_score_is_the_closed_loop_tracking_of_the_adapted_models(monkeypatch):
    """A tiny search job on the CI config scored on control: each step size's score is the
    geometric mean over the validation targets of (tracking cost of the adapted model) / (the
    NMPC's); the held-out loss stays as prediction_score; the NMPC's yardstick is the same
    closed loop run again (deterministic). That the in-process loop is the experiment's is
    test_experiment's check (retrack reproduces every recorded tracking cost)."""
    import numpy as np
    from metampc_bringup.studies import learning_setup
    config = os.path.join(ROOT, 'config', 'ci.yaml')
    settings = learning_setup.settings_from(config, 2, 2, {'batch_size': 4}, control=True)
    scoring = settings.control
    assert len(scoring.nmpc) == 2 and all(0 < c < math.inf for c in scoring.nmpc)
    assert learning_setup.track(scoring, settings.thetas[0], None) == scoring.nmpc[0]
    # This process's worker state (other tests' settings and validation sets) set aside.
    monkeypatch.setattr(learning_setup, '_VALIDATIONS', {})
    monkeypatch.setattr(learning_setup, '_SETTINGS', None)
    learning_setup.use(settings, 1)
    job = learning_setup.Job('maml', 0, {'inner_steps': 2}, 3, (0.05,), 'search')
    out = learning_setup.run_job(job)
    entry = out['adapt'][0]
    assert len(entry['control_ratios']) == 2 and entry['prediction_score'] == pytest.approx(
        float(np.mean(entry['heldout_final'])))
    assert entry['score'] == pytest.approx(float(np.exp(np.mean(np.log(
        entry['control_ratios'])))))
    assert out['score'] == entry['score']


def test_a_job_above_its_pruning_threshold_stops_there_and_says_so(tiny_config, direct):
    """run_job with the median pruner's thresholds (Job.prune_above): the reports are the
    means of every 10 losses of the same meta-training run by hand (seeded); a threshold just
    below the best of the first two reports stops meta-training at step 20 (two reports, no
    adaptation, score inf, pruned_at 20); one just above lets the job run to its end with
    the results of the job without thresholds."""
    import numpy as np
    from dataclasses import replace
    from metampc_bringup.studies import learning_setup
    from metampc_learner.meta_train import meta_train
    settings = settings_from(str(tiny_config), 1, 2, {'batch_size': 2, 'curvature': CURVATURE})
    job = Job('maml', 0, {'inner_steps': 2}, 30, (0.05,), 'search')
    full = direct(settings, job)
    val = learning_setup.validation(job.source_seed, job.nssm)
    losses = meta_train(val.model, val.source, learning_setup.meta_config(job, settings)).losses
    assert full['meta_loss_reports'] == pytest.approx(
        [float(np.mean(losses[i:i + 10])) for i in (0, 10, 20)], rel=1e-12)
    best = min(full['meta_loss_reports'][:2])
    stopped = direct(settings, replace(job, prune_above=(math.nan, best * (1 - 1e-9), 0.0)))
    assert stopped['pruned_at'] == 20 and stopped['score'] == math.inf
    assert stopped['meta_loss_reports'] == full['meta_loss_reports'][:2]
    assert stopped['adapt'] == [] and 'meta_final_loss' not in stopped
    kept = direct(settings, replace(job, prune_above=(math.nan, best * (1 + 1e-9), math.inf)))
    assert kept == full


def test_tune_stopped_by_ctrl_c_resumes_without_running_the_finished_trials_again(
        tmp_path, tiny_config):
    """scripts/tune.py as a user runs it, SIGINT to its process group once two jobs have
    landed: exit 130 and one line; the same command then runs only the jobs that were not
    finished (its log's counts), leaves the finished ones' results as they were, keeps the
    told trials of the studies as they were, and ends 0 with every trial told."""
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / 'tuning.json'
    command = [sys.executable, str(Path(ROOT) / 'scripts' / 'tune.py'), '--config',
               str(tiny_config), *TINY_SEARCH, '--jobs', '1', '--out', str(out)]
    cache = tmp_path / 'tuning.study' / 'cache'
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not (cache.is_dir() and len(list(cache.glob('*.json'))) >= 2):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)      # a terminal's Ctrl-C
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == \
        'tune: interrupted; the finished jobs are cached: the same command resumes', stderr
    finished = {p.name: p.stat().st_mtime_ns for p in cache.glob('*.json')}
    storage = open_storage(str(tmp_path / 'tuning.study' / 'study.journal'))

    def told():
        return {(s.study_name, t.number): (t.state, t.value, t.datetime_complete)
                for s in optuna.get_all_study_summaries(storage)
                for t in optuna.load_study(study_name=s.study_name, storage=storage)
                .get_trials(states=(optuna.trial.TrialState.COMPLETE,))}
    before = told()
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    ran = sum(int(n) for n in re.findall(r': (\d+) job\(s\) to run', done.stderr))
    everything = {p.name for p in cache.glob('*.json')}
    assert len(everything) == 9 and ran == 9 - len(finished) > 0, done.stderr
    assert {n: (cache / n).stat().st_mtime_ns for n in finished} == finished
    after = told()
    assert {k: after[k] for k in before} == before
    assert len(after) == 2 * (2 + 2)     # every trial of both studies told


def test_a_study_adapts_by_the_experiments_rule(tmp_path, tiny_config, direct):
    """Under the experiment's ``adapt_rule: gauss_newton`` a job scores one step size, and
    its held-out losses are those of the learner's own Levenberg-Marquardt adaptation
    (``adapt.supervised`` with that rule on the job's validation data), not the gradient's."""
    from dataclasses import replace as with_fields
    from metampc_bringup.studies import learning_setup
    from metampc_learner.adapt import supervised
    config = tmp_path / 'gauss_newton.yaml'
    config.write_text(tiny_config.read_text().replace(
        'learner: {', 'learner: {adapt_rule: gauss_newton, adapt_cg_steps: 4, '))
    settings = settings_from(str(config), 1, 2)
    assert (settings.learner.adapt.rule, settings.learner.adapt.cg_steps) == ('gauss_newton', 4)
    result = direct(settings, Job('supervised', 0, {}, 0, ADAPT_LRS, 'search'))
    assert [a['lr'] for a in result['adapt']] == [ADAPT_LRS[0]]
    from metampc_learner.data import Windows
    val = learning_setup.validation(learning_setup.VALIDATION_SEED, {})
    train, held = (Windows.from_trajectories(part[0], val.model.norm, val.model.config)
                   for part in (val.train, val.heldout))
    step = with_fields(settings.learner.adapt, steps=2, lr=ADAPT_LRS[0], gamma=0.0)
    expected = supervised(val.model, train, held, step,
                          seed=learning_setup.VALIDATION_SEED).heldout_loss[-1]
    gradient = supervised(val.model, train, held, with_fields(step, rule='gradient'),
                          seed=learning_setup.VALIDATION_SEED).heldout_loss[-1]
    assert result['adapt'][0]['heldout_final'] == [expected] != [gradient]
