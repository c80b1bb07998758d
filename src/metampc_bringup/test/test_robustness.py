"""scripts/robustness.py: MetaConfig overrides (--set), adaptation scores (--adapt), resuming
from the cache, and one error line with exit status 2 on bad arguments."""
import importlib.util
import json
import os
from pathlib import Path

import pytest

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


def test_override_adapt_and_resume(tmp_path, capsys, tiny_config):
    config = tiny_config
    config.write_text(config.read_text().split('meta_train:')[0] + SHORT)
    out = tmp_path / 'out'
    args = ['--config', str(config), '--out', str(out), '--methods', 'maml', '--seeds', '2',
            '--jobs', '1', '--adapt', '--set', 'lr_schedule=cosine', '--set', 'lr_inner=0.03']
    assert _script().main(args) == 0
    first = json.loads((out / 'robustness.json').read_text())
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


@pytest.mark.parametrize('setting', ['foo=1', 'lr_schedule=linear', 'vectorise=maybe',
                                     'iterations=3', 'lr_outer=fast', 'lr_outer', 'gamma=-1'])
def test_bad_set_exits_2_with_one_line(tmp_path, capsys, setting, tiny_config):
    config = tiny_config
    out = tmp_path / 'out'
    assert _script().main(['--config', str(config), '--out', str(out), '--set', setting]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not os.path.exists(out)
