"""`ros2 run metampc_bringup adapt_offline` as a user runs it, on the stand-in robot's bag and on a
logger's CSV of it: the adapted checkpoint loaded the way the controller loads a model (the
NssmWeights message, decoded and built into predictor and MPC), and its T-step predictions of
a fresh episode of the same robot (an independent answer: data the adaptation never saw)
against the meta-model's; bad input is one line and exit status 2."""
import json
import subprocess

import numpy as np
import pytest
import yaml

from metampc_bringup.adapt_offline import main
from robot_recording import MAPPING, tstep_rmse, write_csv

pytestmark = pytest.mark.xdist_group('robot_recording')
LR = '1.0'      # the tuned adaptation rate of the experiments (config/default.yaml adapt)


def controller_predictor(path: str):
    """The model of a checkpoint as the controller gets and builds it."""
    from metampc_bringup.soak.weights_messages import checkpoint_weights
    from metampc_controller.controller_core import build_model
    from metampc_controller.mpc import MpcConfig
    from metampc_model.weights_codec import fields_of, weights_from_fields
    msg = checkpoint_weights(path)
    bundle = build_model(weights_from_fields(fields_of(msg)), msg.version, msg.method,
                         msg.stage, MpcConfig(), 1, 2)
    return msg, bundle.predictor


def errors_on_fresh_data(path: str, fresh) -> np.ndarray:
    """Per output, the RMSE of the T-step predictions of the fresh episode (T = 5, the
    meta-model's; the message carries no T)."""
    u, y = fresh
    _, predictor = controller_predictor(path)
    return tstep_rmse(predictor, u, y, 5)


def test_adapt_offline_on_the_robot_bag_as_a_user_runs_it(robot_bag, robot_meta, fresh_robot,
                                                          tmp_path):
    out = tmp_path / 'adapted.pt'
    run = subprocess.run(['ros2', 'run', 'metampc_bringup', 'adapt_offline', str(robot_bag),
                          MAPPING, robot_meta, '--out', str(out), '--samples', '300', '--lr', LR],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert '| used: training / held out | 240 / 60 |' in run.stdout
    assert 'adapt_offline: step 20/20: held-out loss' in run.stderr
    report = json.loads(out.with_suffix('.json').read_text())
    assert out.with_suffix('.md').read_text() == run.stdout
    msg, _ = controller_predictor(str(out))
    assert (msg.method, msg.stage) == ('maml', 'adapted')
    meta, ours = (errors_on_fresh_data(p, fresh_robot) for p in (robot_meta, str(out)))
    print(f'fresh episode, T-step RMSE [q, qd]: meta-model {meta}, adapted {ours}')
    assert np.all(ours < 0.7 * meta), (meta, ours)
    held = report['heldout']
    assert held['adapted']['loss'] < 0.5 * held['meta']['loss']
    # The linear ARX of the same 240 samples, flown the same way: the robot near its
    # operating point is close to linear, and least squares finds what 20 steps do not.
    arx = tmp_path / 'arx.pt'
    assert main([str(robot_bag), MAPPING, robot_meta, '--out', str(arx), '--samples', '300',
                 '--method', 'arx']) == 0
    msg, _ = controller_predictor(str(arx))
    assert (msg.method, msg.stage, msg.train_steps) == ('arx', 'adapted', 0)
    linear = errors_on_fresh_data(str(arx), fresh_robot)
    print(f'fresh episode, T-step RMSE [q, qd]: arx {linear}')
    assert np.all(linear < 0.1 * ours), (ours, linear)


def test_adapt_offline_on_a_csv_of_the_robot(robot_session, robot_meta, fresh_robot, tmp_path,
                                             capsys):
    csv = write_csv(robot_session, tmp_path / 'robot.csv', nan_row=100, gap=(200, 210))
    out = tmp_path / 'from_csv.pt'
    assert main([str(csv), MAPPING, robot_meta, '--out', str(out), '--lr', LR,
                 '--samples', '300']) == 0
    report = json.loads(out.with_suffix('.json').read_text())
    skipped = report['samples']['skipped']
    assert skipped['stale'] >= 5 and skipped['nan'] == 1 and skipped['no_input'] == 1
    assert report['clock'] == "column 'time', s" and report['kind'] == 'csv'
    meta, ours = (errors_on_fresh_data(p, fresh_robot) for p in (robot_meta, str(out)))
    print(f'fresh episode, T-step RMSE [q, qd]: meta-model {meta}, adapted from CSV {ours}')
    assert np.all(ours < 0.7 * meta), (meta, ours)
    assert '| used: training / held out | 240 / 60 |' in capsys.readouterr().out


def bad_mapping(tmp_path, change) -> str:
    with open(MAPPING) as f:
        data = yaml.safe_load(f)
    change(data)
    path = tmp_path / 'mapping.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_bad_input_is_one_line_and_exit_status_2(robot_bag, robot_session, robot_meta,
                                                 tmp_path, capsys):
    def field(data):
        data['outputs'][1]['field'] = 'velocty[0]'

    def topic(data):
        data['command']['topic'] = '/arm/commands'

    def kind(data):
        data['command']['type'] = 'geometry_msgs/msg/Twist'
        data['command']['inputs'][0]['field'] = 'linear.x'

    def renamed(data):
        data['command']['inputs'][0]['name'] = 'torque'

    def third(data):
        data['outputs'].append(dict(data['outputs'][0], name='q2'))

    csv = str(write_csv(robot_session, tmp_path / 'robot.csv'))
    cases = [
        (str(robot_bag), field, "outputs[1].field: sensor_msgs/msg/JointState has no field "
         "'velocty' (its fields: header, name, position, velocity, effort)"),
        (str(robot_bag), topic, f'command.topic: /arm/commands is not in {robot_bag} (its '
         'topics: '),
        (str(robot_bag), kind, 'command.type: /effort_controller/commands is '
         f'std_msgs/msg/Float64MultiArray in {robot_bag}, not geometry_msgs/msg/Twist'),
        (csv, renamed, f"{csv}: no column 'torque' (command.inputs[0].name; its columns: "
         'time, q, qd, tau)'),
        (csv, third, f'{robot_meta}: a model of 1 input(s) and 2 output(s); the mapping '),
    ]
    for recording, change, message in cases:
        mapping = bad_mapping(tmp_path, change)
        assert main([recording, mapping, robot_meta, '--out', str(tmp_path / 'x.pt')]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f'adapt_offline: error: {message}'), err
        assert err.count('\n') == 1, err
    assert not (tmp_path / 'x.pt').exists()
    run = subprocess.run(['ros2', 'run', 'metampc_bringup', 'adapt_offline', str(robot_bag),
                          bad_mapping(tmp_path, topic), robot_meta, '--out',
                          str(tmp_path / 'x.pt')], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ''
    assert run.stderr.startswith('adapt_offline: error: command.topic: /arm/commands is not')
    assert run.stderr.count('\n') == 1, run.stderr


def test_the_gain_check_of_the_config_refuses_a_model_of_the_wrong_sign(
        robot_bag, robot_meta, tmp_path):
    """Issue 53: adapt_offline wrote a model whose gain had the wrong sign where the Adapt
    service would have refused it. With --config's gain_check on (config/default.yaml's),
    the robot's meta-model with its B negated, taken as it is (--steps 0), is refused and the
    checkpoint written is the one --method arx writes for the same samples."""
    import torch
    from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
    ckpt = load_checkpoint(robot_meta)
    flipped = str(tmp_path / 'flipped.pt')
    save_checkpoint(flipped, ckpt.model, {**ckpt.params, 'B': -ckpt.params['B']}, ckpt.info)
    config = tmp_path / 'experiment.yaml'
    config.write_text('learner: {gain_check: true}\n')
    out, arx = tmp_path / 'adapted.pt', tmp_path / 'arx.pt'
    run = subprocess.run(['ros2', 'run', 'metampc_bringup', 'adapt_offline', str(robot_bag),
                          MAPPING, flipped, '--out', str(out), '--samples', '300', '--steps',
                          '0', '--config', str(config)], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert 'disagrees in sign' in run.stderr and 'the ARX written in its place' in run.stderr
    report = json.loads(out.with_suffix('.json').read_text())
    assert report['fallback'] == 'arx' and report['settings_from'] == (
        f'steps given, gain_check from {config}')
    assert main([str(robot_bag), MAPPING, robot_meta, '--out', str(arx), '--samples', '300',
                 '--method', 'arx']) == 0
    written, expected = load_checkpoint(str(out)), load_checkpoint(str(arx))
    assert written.model.config == expected.model.config
    assert all(torch.equal(written.params[k], v) for k, v in expected.params.items())


def test_the_old_name_says_where_the_command_went():
    run = subprocess.run(['ros2', 'run', 'metampc_learner', 'adapt_offline', 'x', 'y', 'z',
                          '--out', 'a.pt'], capture_output=True, text=True, timeout=60)
    assert (run.returncode, run.stdout) == (2, '')
    assert run.stderr == ('adapt_offline: moved: ros2 run metampc_bringup adapt_offline (the '
                          'same arguments); this name will be removed in the next release\n')
