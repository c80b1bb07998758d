"""scripts/robustness.py: MetaConfig overrides (--set), adaptation scores (--adapt), the runs of
the process pool before (direct calls) on the embedded cluster (--jobs 2) and on a loopback
scheduler (--scheduler), resuming from the cache, and one error line with exit status 2 on bad
arguments."""
import importlib.util
import json
import math
import os
from pathlib import Path

import pytest

from metampc_bringup.experiment_config import load
from metampc_bringup.studies.learning_setup import settings_from
from metampc_bringup.studies.robustness import robustness_jobs, robustness_summary
from metampc_bringup.studies.tuning import TuneConfig
from metampc_testing import loopback_dask

ROOT = Path(__file__).resolve().parents[3]
# The shared tiny experiment (conftest), with short meta-training and MAML's adaptation.
SHORT = """
meta_train:
  imaml: {iterations: 4, batch_size: 2, lr_outer: 0.005, cg_steps: 2}
  maml: {iterations: 4, batch_size: 2, lr_outer: 0.01}
adapt:
  maml: {steps: 3, lr: 0.2}
"""


def _script():
    spec = importlib.util.spec_from_file_location('robustness', ROOT / 'scripts' /
                                                  'robustness.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _direct_runs(config, overrides, direct):
    """The runs of 'maml' on seeds 0, 1 with --adapt, called directly (the old pool's)."""
    tuning = TuneConfig()
    settings = settings_from(str(config), tuning.thetas, tuning.adapt_steps)
    jobs = robustness_jobs(load(str(config)), ['maml'], [0, 1], {}, overrides, adapt=True)
    return [direct(settings, job) for job in jobs]


def test_override_adapt_and_resume(tmp_path, capsys, tiny_config, direct, untimed):
    config = tiny_config
    config.write_text(config.read_text().split('meta_train:')[0] + SHORT)
    out = tmp_path / 'out'
    args = ['--config', str(config), '--out', str(out), '--methods', 'maml', '--seeds', '2',
            '--jobs', '2', '--adapt', '--set', 'lr_schedule=cosine', '--set', 'lr_inner=0.03']
    assert _script().main(args) == 0
    first = json.loads((out / 'robustness.json').read_text())
    assert first['jobs'] == 2
    assert [untimed(r) for r in first['runs']] == _direct_runs(
        config, {'lr_schedule': 'cosine', 'lr_inner': 0.03}, direct)
    assert first['overrides'] == {'lr_schedule': 'cosine', 'lr_inner': 0.03}
    runs = first['runs']
    assert [r['source_seed'] for r in runs] == [0, 1]
    assert all(r['hyper']['lr_schedule'] == 'cosine' and r['hyper']['lr_inner'] == 0.03
               and r['hyper']['lr_outer'] == 0.01 for r in runs)
    # --adapt: one step size, the experiment's (adapt.maml.lr), scored on the targets.
    assert all([a['lr'] for a in r['adapt']] == [0.2] for r in runs)
    summary = first['summary']['maml']
    assert summary['score'] == [r['score'] for r in runs]
    assert summary['mean_score'] == pytest.approx(sum(summary['score']) / 2)
    cached = {p: p.stat().st_mtime_ns for p in (out / 'cache').iterdir()}
    assert len(cached) == 2
    assert _script().main(args) == 0           # every run from the cache: nothing rewritten
    assert {p: p.stat().st_mtime_ns for p in (out / 'cache').iterdir()} == cached
    again = json.loads((out / 'robustness.json').read_text())
    assert again['runs'] == runs


def test_runs_on_a_loopback_scheduler_are_those_of_direct_calls(tmp_path, tiny_config, direct,
                                                                untimed):
    config = tiny_config
    config.write_text(config.read_text().split('meta_train:')[0] + SHORT)
    out = tmp_path / 'out'
    with loopback_dask(tmp_path / 'worker.log') as (address, _):
        assert _script().main(['--config', str(config), '--out', str(out), '--methods', 'maml',
                               '--seeds', '2', '--adapt', '--scheduler', address]) == 0
    report = json.loads((out / 'robustness.json').read_text())
    assert report['scheduler'] == address and report['jobs'] == 1
    assert [untimed(r) for r in report['runs']] == _direct_runs(config, {}, direct)


@pytest.mark.parametrize('setting', ['foo=1', 'lr_schedule=linear', 'vectorise=maybe',
                                     'iterations=3', 'lr_outer=fast', 'lr_outer', 'gamma=-1'])
def test_bad_set_exits_2_with_one_line(tmp_path, capsys, setting, tiny_config):
    config = tiny_config
    out = tmp_path / 'out'
    assert _script().main(['--config', str(config), '--out', str(out), '--set', setting]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not os.path.exists(out)


def test_divergence_by_each_loss_against_its_own_median():
    """Five hand-made runs: the final loss of seed 3 is 12x the median (1.0), seed 4's is
    not finite; by the returned loss only seed 2 (11x); by the common adapted score only seed 1
    (10.5x the median 0.1), seed 0 at exactly 10x is not above it."""
    def run(seed, final, returned, score):
        return {'method': 'maml', 'source_seed': seed, 'meta_final_loss': final,
                'meta_returned_loss': returned, 'adapt': [{'lr': 0.2}], 'score': score}
    runs = [run(0, 1.0, 1.0, 1.0), run(1, 1.0, 1.0, 1.05), run(2, 1.0, 11.0, 0.1),
            run(3, 12.0, 1.0, 0.1), run(4, math.inf, 1.0, 0.1)]
    summary = robustness_summary(runs)['maml']
    assert summary['diverged'] == [3, 4] and summary['diverged_returned'] == [2]
    assert summary['median_score'] == 0.1 and summary['diverged_score'] == [1]
    assert summary['n_diverged_score'] == 1
