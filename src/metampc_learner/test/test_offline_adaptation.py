"""Adaptation from a recording, the core: every sample of the robot's bag accounted for, the
split as the learner node's, the learner's own adaptation and its checkpoint; the reported
T-step RMSE against the controller's numpy predictor; methods and settings resolved, and inputs
that do not fit refused with one line."""
from dataclasses import replace
import json

import numpy as np
import pytest
import torch

from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import Trajectory, Windows
from metampc_learner.grid_samples import REASONS
from metampc_learner.learner_params import default_config
from metampc_learner.offline_adaptation import (adapt_settings, Experiment, OfflineConfig,
                                                OfflineError, resolve_method, run_offline,
                                                tstep_rmse)

pytestmark = pytest.mark.xdist_group('robot_recording')


@pytest.fixture(scope='module')
def mapping_file():
    from robot_recording import MAPPING
    return MAPPING


def test_every_sample_is_accounted_for_and_the_checkpoint_is_the_adapted_one(robot_bag,
                                                                             robot_meta,
                                                                             mapping_file,
                                                                             tmp_path):
    out = str(tmp_path / 'adapted.pt')
    lines = []
    report = run_offline(str(robot_bag), mapping_file, robot_meta, out,
                         OfflineConfig(steps=5, lr=1.0, samples=300, holdout=0.25), lines.append)
    s = report['samples']
    assert s['grid'] == s['usable'] + sum(s['skipped'].values()) == 500
    assert set(s['skipped']) == set(REASONS)
    assert (s['used'], s['train'], s['heldout']) == (300, 225, 75)
    assert s['unused'] == s['usable'] - 300
    assert sum(r['count'] for r in s['skipped_runs']) == sum(s['skipped'].values())
    curve, held = report['curve'], report['heldout']
    assert len(curve['train_loss']) == len(curve['heldout_loss']) == 6
    # Two float32 code paths of one mean over the windows (the model's parameters, adapt's
    # flat vector): equal to float32 rounding, 1.4e-6 apart on one machine.
    assert held['meta']['loss'] == pytest.approx(curve['heldout_loss'][0], rel=1e-5)
    assert held['adapted']['loss'] == curve['heldout_loss'][-1] < held['meta']['loss']
    assert len(held['adapted']['rmse']) == 2 and report['loss_horizon'] == 5
    assert (report['method'], report['settings_from']) == ('maml', 'steps given, lr given')
    info = load_checkpoint(out).info
    assert (info['method'], info['stage'], info['train_steps'], info['train_samples'],
            info['dt']) == ('maml', 'adapted', 5, 225, 0.1)
    assert info['heldout_loss'] == held['adapted']['loss']
    with open(out[:-3] + '.json') as f:
        assert json.load(f) == report
    with open(out[:-3] + '.md') as f:
        assert f.read().startswith('# adapt_offline: maml on robot\n')
    assert lines[-1].startswith('step 5/5: held-out loss ')


def test_a_recording_cut_short_is_adapted_on_and_the_report_says_so(robot_session, robot_meta,
                                                                    mapping_file, tmp_path):
    from robot_recording import write_recording
    data = write_recording(robot_session, tmp_path / 'whole.mcap', 8192).read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:len(data) // 2])
    lines = []
    report = run_offline(str(cut), mapping_file, robot_meta, str(tmp_path / 'a.pt'),
                         OfflineConfig(steps=1, lr=1.0, samples=100, holdout=0.25), lines.append)
    assert report['cut_short'].startswith(f'{cut} was cut short') and report['cut_short'] in lines
    assert 0 < report['samples']['grid'] < 500     # the finished file's grid: 500 samples
    with open(tmp_path / 'a.md') as f:
        assert f'**{report["cut_short"]}.**' in f.read()


def test_kept_saturated_inputs_leave_no_sample_skipped_for_it(robot_bag, robot_meta,
                                                              mapping_file, tmp_path):
    report = run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 'a.pt'),
                         OfflineConfig(steps=0, keep_saturated=True))
    assert report['samples']['skipped']['input_saturated'] == 0
    assert report['samples']['keep_saturated'] is True
    held = report['heldout']
    assert held['adapted']['loss'] == pytest.approx(held['meta']['loss'], rel=1e-5)
    assert held['adapted']['rmse'] == pytest.approx(held['meta']['rmse'], rel=1e-5)


def test_the_reported_rmse_is_the_controller_predictors_error(robot_meta, fresh_robot):
    from robot_recording import tstep_rmse as predictor_rmse
    ckpt = load_checkpoint(robot_meta)
    u, y = fresh_robot
    windows = Windows.from_trajectories([Trajectory(np.arange(1, len(u) + 1), u, y)],
                                        ckpt.model.norm, ckpt.model.config)
    ours = tstep_rmse(ckpt.model, ckpt.params, windows)
    theirs = predictor_rmse(NssmPredictor(ckpt.model.config, ckpt.model.norm, ckpt.params),
                            u, y, ckpt.model.config.loss_horizon)
    np.testing.assert_allclose(ours, theirs, rtol=1e-4)


def test_supervised_trains_from_seeded_random_weights(robot_bag, robot_meta, mapping_file,
                                                      tmp_path):
    def run(seed):
        return run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 's.pt'),
                           OfflineConfig(method='supervised', steps=2, gamma=5.0, seed=seed))
    a, b, c = run(3), run(3), run(4)
    assert a['curve'] == b['curve'] and a['curve'] != c['curve']
    assert (a['method'], a['gamma']) == ('supervised', 0.0)
    assert a['curve']['heldout_loss'][0] != pytest.approx(a['heldout']['meta']['loss'])


def test_arx_is_fitted_without_steps_and_reported_in_its_own_scaling(
        robot_bag, robot_meta, mapping_file, fresh_robot, tmp_path):
    from robot_recording import tstep_rmse as predictor_rmse
    out = str(tmp_path / 'arx.pt')
    report = run_offline(str(robot_bag), mapping_file, robot_meta, out,
                         OfflineConfig(method='arx', steps=7, samples=300, holdout=0.25))
    assert (report['method'], report['steps'], report['gamma']) == ('arx', 0, 0.0)
    assert report['settings_from'] == 'none (least squares)'
    assert len(report['curve']['heldout_loss']) == 1 and report['curve']['rates'] == []
    ckpt = load_checkpoint(out)
    assert (ckpt.info['method'], ckpt.info['train_steps'], ckpt.info['train_samples']) == (
        'arx', 0, 225)
    cfg = ckpt.model.config
    assert cfg.n_z == 2 * (cfg.n_y + cfg.n_u) - cfg.n_u and not cfg.stable_latent    # p = 2
    # Its held-out RMSE is measured in its own scaling: l_SSM = sum_i (rmse_i / y_std_i)^2.
    held = report['heldout']['adapted']
    assert sum((r / s) ** 2 for r, s in zip(held['rmse'], ckpt.model.norm.y_std)) == \
        pytest.approx(held['loss'], rel=1e-4)
    u, y = fresh_robot          # and the checkpoint is the NSSM the controller flies
    windows = Windows.from_trajectories([Trajectory(np.arange(1, len(u) + 1), u, y)],
                                        ckpt.model.norm, ckpt.model.config)
    np.testing.assert_allclose(
        tstep_rmse(ckpt.model, ckpt.params, windows),
        predictor_rmse(NssmPredictor(ckpt.model.config, ckpt.model.norm, ckpt.params), u, y,
                       ckpt.model.config.loss_horizon), rtol=1e-3)   # torch float32: its RMSE
    # is ~1e-4 of the outputs' scale, so the float32 rounding shows in the 4th digit


def test_the_method_is_the_checkpoints_or_supervised():
    assert resolve_method('', {'method': 'imaml'}, 'm.pt') == 'imaml'
    assert resolve_method('', {}, 'm.pt') == 'imaml'
    assert resolve_method('supervised', {'method': 'maml'}, 'm.pt') == 'supervised'
    assert resolve_method('arx', {'method': 'oracle'}, 'm.pt') == 'arx'
    with pytest.raises(OfflineError, match=r'^--method imaml: m.pt holds a maml meta-model '
                       r'\(use --method maml, supervised or arx\)$'):
        resolve_method('imaml', {'method': 'maml'}, 'm.pt')
    with pytest.raises(OfflineError, match="^m.pt holds a 'oracle' model, not a meta-model"):
        resolve_method('', {'method': 'oracle'}, 'm.pt')


def _experiment(learner_keys=(), requests=None, **learner):
    """The settings an experiment file gives (as ``metampc_bringup.adapt_offline`` reads
    them): the learner's defaults with `learner`'s fields replaced."""
    cfg = default_config()
    adapt = {k: learner.pop(k) for k in ('rule', 'cg_steps') if k in learner}
    return Experiment('experiment.yaml', replace(cfg, adapt=replace(cfg.adapt, **adapt),
                                                 **learner), requests or {}, learner_keys)


def test_settings_come_from_the_command_line_then_the_experiment_then_the_defaults():
    experiment = _experiment(requests={'maml': {'steps': 7, 'lr': 0.2}, 'imaml': {'steps': 9}})
    settings, where = adapt_settings('maml', OfflineConfig(lr=0.5, experiment=experiment))
    assert (settings.adapt.steps, settings.adapt.lr, settings.adapt.gamma) == (7, 0.5, 0.0)
    assert where == 'lr given, steps from experiment.yaml'
    settings, where = adapt_settings('supervised', OfflineConfig(experiment=experiment))
    assert (settings.adapt.steps, settings.adapt.lr, where) == (20, 0.05,
                                                                "the learner's defaults")
    assert (settings.arx_order, settings.gain_check, settings.seed) == (2, False, 0)
    settings, where = adapt_settings('maml', OfflineConfig(
        arx_order=3, seed=4, experiment=_experiment(('gain_check',), gain_check=True)))
    assert (settings.arx_order, settings.gain_check, settings.seed) == (3, True, 4)
    assert where == 'arx_order given, gain_check from experiment.yaml'
    with pytest.raises(OfflineError, match='^adaptation settings: lr'):
        adapt_settings('maml', OfflineConfig(lr=-1.0))


def test_the_rule_comes_from_the_command_line_then_the_experiments_learner():
    experiment = _experiment(('adapt_rule', 'adapt_cg_steps'), rule='gauss_newton', cg_steps=12)
    settings, where = adapt_settings('imaml', OfflineConfig(experiment=experiment))
    assert (settings.adapt.rule, settings.adapt.cg_steps) == ('gauss_newton', 12)
    assert where == 'rule from experiment.yaml, cg_steps from experiment.yaml'
    settings, where = adapt_settings('imaml', OfflineConfig(rule='gradient',
                                                            experiment=experiment))
    assert (settings.adapt.rule, settings.adapt.cg_steps) == ('gradient', 12)
    with pytest.raises(OfflineError, match='^adaptation settings: rule must be one of '
                       "gradient, gauss_newton, got 'newton'$"):
        adapt_settings('imaml', OfflineConfig(rule='newton'))
    with pytest.raises(OfflineError, match='^adaptation settings: cg_steps'):
        adapt_settings('imaml', OfflineConfig(rule='gauss_newton', cg_steps=0))


def test_a_gauss_newton_rule_of_the_experiment_is_the_one_that_adapts(robot_bag, robot_meta,
                                                                      mapping_file, tmp_path):
    """The experiment's rule and the same rule given run the same steps (bit for bit), and
    they are Levenberg-Marquardt steps: rates 1 / damping, above --lr's backtracked ones."""
    experiment = _experiment(('adapt_rule', 'adapt_cg_steps'), rule='gauss_newton', cg_steps=5)
    lines = []
    run = dict(steps=2, lr=1.0, samples=300, holdout=0.25)
    listed = run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 'a.pt'),
                         OfflineConfig(**run, experiment=experiment), lines.append)
    given = run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 'b.pt'),
                        OfflineConfig(**run, rule='gauss_newton', cg_steps=5))
    assert (listed['rule'], listed['cg_steps']) == ('gauss_newton', 5)
    assert listed['curve'] == given['curve']
    rates = listed['curve']['rates']
    assert all(r > 1.0 for r in rates if r)
    assert listed['heldout']['adapted']['loss'] < listed['heldout']['meta']['loss']
    assert any('2 Levenberg-Marquardt steps (5 CG iterations each)' in line for line in lines)


def test_an_adapted_model_of_the_wrong_gain_sign_is_refused_and_the_arx_written(
        robot_bag, robot_meta, mapping_file, tmp_path):
    """Issue 53: the gain check applied through the Adapt service only. With the learner's
    gain_check on, the robot's meta-model taken as it is (0 steps) agrees in sign with the
    ARX of its samples and is written; its B negated (the gain's sign flipped) it is refused
    and the checkpoint written is the ARX that --method arx fits on the same samples."""
    ckpt = load_checkpoint(robot_meta)
    flipped = str(tmp_path / 'flipped.pt')
    save_checkpoint(flipped, ckpt.model, {**ckpt.params, 'B': -ckpt.params['B']}, ckpt.info)
    check = dict(steps=0, samples=300, holdout=0.25,
                 experiment=_experiment(('gain_check',), gain_check=True))
    kept = run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 'kept.pt'),
                       OfflineConfig(**check))
    assert kept['fallback'] == '' and kept['gain_check'].startswith('gain check passed')
    lines = []
    out = str(tmp_path / 'refused.pt')
    refused = run_offline(str(robot_bag), mapping_file, flipped, out, OfflineConfig(**check),
                          lines.append)
    assert refused['fallback'] == 'arx' and 'disagrees in sign' in refused['gain_check']
    assert any(line.endswith('the ARX written in its place') for line in lines)
    arx = str(tmp_path / 'arx.pt')
    fitted = run_offline(str(robot_bag), mapping_file, robot_meta, arx,
                         OfflineConfig(method='arx', samples=300, holdout=0.25))
    written, expected = load_checkpoint(out), load_checkpoint(arx)
    assert written.model.config == expected.model.config
    assert all(torch.equal(written.params[k], expected.params[k]) for k in expected.params)
    assert (written.info['method'], written.info['train_steps']) == ('maml', 0)
    assert refused['heldout']['adapted'] == fitted['heldout']['adapted']
    with open(out[:-3] + '.md') as f:
        assert '**gain check: its steady-state gain' in f.read()


def test_a_checkpoint_of_other_sizes_or_too_few_samples_is_one_line(robot_bag, robot_meta,
                                                                    mapping_file, tmp_path):
    three = str(tmp_path / 'three.pt')
    config = NssmConfig(n_y=3, history=5, loss_horizon=5, hidden=(8,), n_z=2)
    model = Nssm(config)
    save_checkpoint(three, model, model.params(), {'method': 'maml'})
    with pytest.raises(OfflineError) as err:
        run_offline(str(robot_bag), mapping_file, three, str(tmp_path / 'x.pt'),
                    OfflineConfig())
    assert str(err.value) == (f'{three}: a model of 1 input(s) and 3 output(s); the mapping '
                              f'{mapping_file} has 1 and 2')
    ckpt, other_dt = load_checkpoint(robot_meta), str(tmp_path / 'dt.pt')
    save_checkpoint(other_dt, ckpt.model, ckpt.params, {**ckpt.info, 'dt': 0.05})
    with pytest.raises(OfflineError) as err:
        run_offline(str(robot_bag), mapping_file, other_dt, str(tmp_path / 'x.pt'),
                    OfflineConfig())
    assert str(err.value) == (f'{other_dt}: a model of dt = 0.05 s; the mapping '
                              f'{mapping_file} samples at dt = 0.1 s')
    with pytest.raises(OfflineError) as err:
        run_offline(str(robot_bag), mapping_file, robot_meta, str(tmp_path / 'x.pt'),
                    OfflineConfig(samples=15))
    assert str(err.value).startswith('too few usable samples: 15 used (')
    assert str(err.value).endswith('each part needs H + T = 10')


def test_unreadable_rows_and_a_short_supply_of_samples_are_said(robot_session, robot_meta,
                                                                mapping_file, tmp_path):
    """Issue 52: the `unreadable` count was only in the JSON; `--samples 300` with fewer
    usable samples said nothing."""
    from robot_recording import write_csv
    csv = write_csv(robot_session, tmp_path / 'robot.csv', nan_row=7)
    lines = []
    report = run_offline(str(csv), mapping_file, robot_meta, str(tmp_path / 'a.pt'),
                         OfflineConfig(steps=0, samples=100000), lines.append)
    s = report['samples']
    assert s['unreadable'] == {'outputs': 1, 'inputs': 0}
    assert f"{csv}: unreadable (a mapped value that is no finite number): 1 of " \
        f"{s['messages']['outputs']} of outputs" in lines
    assert f"--samples 100000: only {s['usable']} usable samples, all used" in lines
    with open(tmp_path / 'a.md') as f:
        assert f"| unreadable outputs (of {s['messages']['outputs']}, no finite number) | 1 |" \
            in f.read().splitlines()
