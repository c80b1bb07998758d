"""adapt_offline's command line refuses bad paths in one line, exit 2, before any work and
before torch is imported (issue 52: an --out into a missing folder ran the whole adaptation,
then a 48-line traceback; an existing --out was overwritten; a missing file took 5 s to refuse,
torch imported first); its --config is read by the experiment configuration's reader."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
MAPPING = os.path.join(ROOT, 'examples', 'joint_robot', 'mapping.yaml')
PROBE = '''
import sys
from metampc_bringup.adapt_offline import main
rc = main(sys.argv[1:])
print(rc, 'torch' in sys.modules)
'''


@pytest.mark.parametrize('case, message', [
    ('recording', '{tmp}/missing.mcap: no such recording'),
    ('mapping', '{tmp}/missing.yaml: no such mapping file'),
    ('checkpoint', '{tmp}/missing.pt: no such checkpoint'),
    ('out exists', '--out {tmp}/adapted.pt exists; results are never overwritten'),
    ('out folder', '--out {tmp}/nowhere/adapted.pt: the folder {tmp}/nowhere does not exist'),
])
def test_bad_paths_are_refused_before_torch_is_imported(case, message, tmp_path):
    files = {name: tmp_path / name for name in ('robot.mcap', 'meta.pt')}
    for path in files.values():
        path.write_text('')
    argv = [str(files['robot.mcap']), MAPPING, str(files['meta.pt']), '--out',
            str(tmp_path / 'adapted.pt'), '--method', 'imaml', '--rule', 'gauss_newton']
    if case == 'recording':
        argv[0] = str(tmp_path / 'missing.mcap')
    elif case == 'mapping':
        argv[1] = str(tmp_path / 'missing.yaml')
    elif case == 'checkpoint':
        argv[2] = str(tmp_path / 'missing.pt')
    elif case == 'out exists':
        (tmp_path / 'adapted.pt').write_text('kept')
    else:
        argv[4] = str(tmp_path / 'nowhere' / 'adapted.pt')
    run = subprocess.run([sys.executable, '-c', PROBE, *argv], capture_output=True, text=True,
                         timeout=120)
    assert run.stdout == '2 False\n', run.stdout + run.stderr
    assert run.stderr == f'adapt_offline: error: {message.format(tmp=tmp_path)}\n'
    if case == 'out exists':
        assert (tmp_path / 'adapted.pt').read_text() == 'kept'


def test_an_unknown_method_or_rule_is_argparse_s_error(tmp_path, capsys):
    from metampc_bringup.adapt_offline import main
    (tmp_path / 'r.mcap').write_text('')
    for option in ('--method', '--rule'):
        with pytest.raises(SystemExit) as end:
            main([str(tmp_path / 'r.mcap'), MAPPING, str(tmp_path / 'r.mcap'), '--out',
                  str(tmp_path / 'a.pt'), option, 'bogus'])
        assert end.value.code == 2
        assert f"argument {option}: invalid choice: 'bogus' (choose from " in \
            capsys.readouterr().err


def test_the_config_is_read_as_the_experiment_runs_it(tmp_path):
    """--config: the learner configuration and Adapt requests of the experiment's run, as
    its reader gives them (issue 53: adapt_offline read the YAML again by hand)."""
    from metampc_bringup.adapt_offline import experiment_settings
    from metampc_bringup.experiment_config import learner_config, load
    from metampc_learner.offline_adaptation import adapt_settings, OfflineConfig
    config = tmp_path / 'experiment.yaml'
    config.write_text('adapt:\n  maml: {steps: 7, lr: 0.2}\n  imaml: {steps: 9}\n'
                      'learner:\n  adapt_rule: gauss_newton\n  adapt_cg_steps: 12\n'
                      '  gain_check: true\n  arx_order: 3\n')
    experiment = experiment_settings(str(config), 5)
    assert experiment.learner == learner_config(load(str(config)), 5)
    settings, where = adapt_settings('maml', OfflineConfig(lr=0.5, seed=5,
                                                           experiment=experiment))
    assert (settings.adapt.steps, settings.adapt.lr, settings.adapt.gamma) == (7, 0.5, 0.0)
    assert (settings.adapt.rule, settings.adapt.cg_steps) == ('gauss_newton', 12)
    assert (settings.gain_check, settings.arx_order, settings.seed) == (True, 3, 5)
    assert where == (f'lr given, steps from {config}, rule from {config}, cg_steps from '
                     f'{config}, arx_order from {config}, gain_check from {config}')
    settings, where = adapt_settings('supervised', OfflineConfig(experiment=experiment))
    assert (settings.adapt.steps, settings.adapt.lr) == (20, 0.05)
    paper = tmp_path / 'paper.yaml'
    paper.write_text('protocol: paper_settings\nmeta_train:\n  imaml: {gamma: 0.3}\n')
    settings, _ = adapt_settings('imaml', OfflineConfig(
        experiment=experiment_settings(str(paper), 0)))
    assert settings.adapt.gamma == 0.3      # the protocol's, as the experiment adapts


def test_a_config_that_does_not_load_is_one_line(tmp_path, capsys):
    from metampc_bringup.adapt_offline import main
    (tmp_path / 'r.mcap').write_text('')
    (tmp_path / 'bad.yaml').write_text('learner: {no_such_parameter: 1}\n')
    rc = main([str(tmp_path / 'r.mcap'), MAPPING, str(tmp_path / 'r.mcap'), '--out',
               str(tmp_path / 'a.pt'), '--config', str(tmp_path / 'bad.yaml')])
    assert rc == 2
    assert capsys.readouterr().err == ('adapt_offline: error: learner: unknown parameter(s) '
                                       'no_such_parameter (docs/learner.md lists them)\n')
