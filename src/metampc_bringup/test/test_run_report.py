"""scripts/replay.py on real recordings: the metrics equal those computed live from the same
messages, the plots exist and have content, and --play republishes with the recorded QoS (a
latched topic replays latched)."""
import json
import math
import os
from pathlib import Path
import subprocess
import sys
import time

from matplotlib import image
from metampc_bringup.analysis.run_report import analyse
from metampc_msgs.msg import NssmWeights, PlantOutput
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

# One xdist worker runs this file and test_recorder_node.py: they share the session's recorded
# closed-loop run (recording_fixtures.closed_loop), built once.
pytestmark = pytest.mark.xdist_group('closed_loop')

REPO = Path(__file__).resolve().parents[3]
REPLAY = str(REPO / 'scripts' / 'replay.py')
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
STREAM = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def close(a, b, path='metrics'):
    """Deep equality, floats to 1e-9 (relative or absolute)."""
    if isinstance(a, dict):
        assert set(a) == set(b), f'{path}: keys {sorted(a)} != {sorted(b)}'
        for key in a:
            close(a[key], b[key], f'{path}.{key}')
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            close(x, y, f'{path}[{i}]')
    elif isinstance(a, float) or isinstance(b, float):
        assert math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9), f'{path}: {a} != {b}'
    else:
        assert a == b, f'{path}: {a!r} != {b!r}'


def with_episodes(msgs):
    """((episode, step), msg) of a step-indexed stream: the episode grows when step falls."""
    episode, last, out = 0, -1, []
    for msg in msgs:
        if msg.step < last:
            episode += 1
        last = msg.step
        out.append(((episode, msg.step), msg))
    return out


def test_replay_metrics_equal_those_computed_live(closed_loop):
    folder = closed_loop.path.parent
    result = subprocess.run([sys.executable, REPLAY, str(folder)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert 'missed ticks' in result.stdout
    report = json.loads((folder / 'report.json').read_text())
    assert report['config'] == closed_loop.run_config
    assert report['recording']['complete']
    close(closed_loop.live, report['metrics'])

    # The main numbers once more, from the messages without the library.
    m, pub = report['metrics'], closed_loop.published
    outputs = dict(with_episodes(pub['/y']))
    errors = np.array([outputs[(e, k + 1)].y[0] - status.y_ref[0]
                       for (e, k), status in with_episodes(pub['/mpc_status'])
                       if (e, k + 1) in outputs])
    assert m['tracking']['samples'] == errors.size > 40
    close(m['tracking']['cost'], float(np.sum(errors ** 2)))
    close(m['tracking']['per_output']['0']['rmse'], float(np.sqrt(np.mean(errors ** 2))))
    last = list(outputs)[-1]
    missed = len(closed_loop.unanswered - {last})
    assert m['ticks'] == {'considered': len(outputs) - 1, 'answered': len(outputs) - 1 - missed,
                          'missed': missed}
    assert missed >= 4     # MISSED and the step before the reset
    assert m['saturated_samples'] == sum(y.saturated for y in pub['/y']) > 0
    info = pub['/plant_info'][-1]
    u = [msg.u[0] for msg in pub['/u']]
    violations = sum(1 for v in u if not info.u_min[0] <= v <= info.u_max[0])
    assert m['input_bounds']['violations'] == violations > 0
    solved = [s.solve_time for s in pub['/mpc_status'] if s.iterations >= 0]
    for name, q in (('p50', 50), ('p99', 99)):
        close(m['solve_time'][name], float(np.percentile(solved, q)))
    close(m['solve_time']['max'], max(solved))
    assert m['fallbacks'] == sum(s.fallback for s in pub['/mpc_status']) > 0
    assert m['model_versions']['published'] == [1, 2]
    assert m['model_versions']['used_by_inputs'] == [1, 2]
    assert [(t['phase'], t['iteration']) for t in m['training']] == [('meta_train', 15),
                                                                     ('adapt', 5)]
    assert sorted(report['plots']) == ['inputs.png', 'outputs.png', 'solve_times.png',
                                       'training_loss.png']
    for name in report['plots']:
        pixels = image.imread(str(folder / name))[..., :3]
        assert pixels.shape[0] > 200 and pixels.shape[1] > 600, name
        assert pixels.std() > 0.05, f'{name} is nearly blank'
        assert np.mean(np.any(pixels < 0.9, axis=-1)) > 0.01, f'{name} has almost no ink'


def test_replay_never_overwrites_a_report_it_did_not_write(closed_loop, tmp_path):
    folder = tmp_path / 'seed_0'
    folder.mkdir()
    recording = folder / 'recording.mcap'
    recording.write_bytes(closed_loop.path.read_bytes())
    foreign = folder / 'report.json'
    foreign.write_text('{"methods": {}}')
    result = subprocess.run([sys.executable, REPLAY, str(folder)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.startswith('replay: error: ') and 'report.json' in result.stderr
    assert foreign.read_text() == '{"methods": {}}'
    assert sorted(p.name for p in folder.iterdir()) == ['recording.mcap', 'report.json']
    out = tmp_path / 'analysis'
    first = analyse(str(recording), out_dir=str(out), plots=False)
    again = analyse(str(recording), out_dir=str(out), plots=False)   # its own: replaced
    assert first == again == json.loads((out / 'report.json').read_text())
    with pytest.raises(FileNotFoundError):
        analyse(str(tmp_path / 'nothing'))


BAD_INPUTS = {   # case: (how to make the input from a good recording, what the line says)
    'markdown': (lambda good, d: _write(d / 'notes.md', b'# notes'), 'is not an MCAP file'),
    'fake mcap': (lambda good, d: _write(d / 'fake.mcap', b'not mcap'), 'is not an MCAP file'),
    'cut to 5 bytes': (lambda good, d: _write(d / 'cut.mcap', good[:5]), 'is not an MCAP file'),
    'cut to 100 bytes': (lambda good, d: _write(d / 'cut.mcap', good[:100]), 'holds no message'),
    'tracked 5': (lambda good, d: _write(d / 'run.mcap', good), 'tracked output(s) [5] out of '
                  'range: the plant has 2 outputs'),
    'experiment folder': (lambda good, d: _write(d / 'seed_0' / 'recording.mcap', good).parent
                          .parent, 'is an experiment run folder with one recording per seed'),
    'play a fake file': (lambda good, d: _write(d / 'fake.mcap', b'not mcap'),
                         'is not an MCAP file'),
}


def _write(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


@pytest.mark.parametrize('case', list(BAD_INPUTS))
def test_bad_input_one_line_exit_2_nothing_written(closed_loop, tmp_path, case):
    make, says = BAD_INPUTS[case]
    folder = tmp_path / 'in'
    target = make(closed_loop.path.read_bytes(), folder)
    before = sorted(p.relative_to(folder) for p in folder.rglob('*'))
    extra = (['--tracked', '5'] if case == 'tracked 5' else
             ['--play'] if case.startswith('play') else [])
    result = subprocess.run([sys.executable, REPLAY, str(target), *extra], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('replay: error: ') and says in lines[0], lines
    assert result.stdout == ''
    assert sorted(p.relative_to(folder) for p in folder.rglob('*')) == before


def record(path, procs, probe, recorders, run, spacing):
    """Publish `run` [(topic, message)] from the probe while a recorder records it."""
    recorder = recorders.start(path, flush_period=0.2)
    pubs = {}
    for topic, msg in run:
        if topic not in pubs:
            pubs[topic] = probe.node.create_publisher(
                type(msg), topic, LATCHED if topic == 'nssm_weights' else STREAM)
    recorders.wait_matched(pubs.values())
    counts = {}
    for topic, msg in run:
        pubs[topic].publish(msg)
        counts['/' + topic] = counts.get('/' + topic, 0) + 1
        time.sleep(spacing)
    recorders.wait_recorded(path, counts)
    assert procs.interrupt(recorder) == 0
    for pub in pubs.values():
        probe.node.destroy_publisher(pub)


def test_play_republishes_with_recorded_qos(tmp_path, procs, probe, recorders):
    run = [('nssm_weights', NssmWeights(version=4, method='maml', stage='meta',
                                        params=[1.5, -2.0]))]
    run += [('y', PlantOutput(step=k, y=[0.5 * k, -k], u_applied=[0.0])) for k in range(40)]
    path = tmp_path / 'play.mcap'
    record(path, procs, probe, recorders, run, spacing=0.05)    # about 2 s of samples

    got = {'y': [], 'weights': []}
    probe.node.create_subscription(PlantOutput, 'y', got['y'].append, STREAM)
    # Volatile samples published before the player has matched the probe's subscription would
    # be lost (with ros2 bag play as here): --wait-subscribers waits for that match. Played at
    # a tenth of the speed (about 20 s) so that the late subscriber below is discovered while
    # the player still runs, however loaded the machine.
    player = subprocess.Popen([sys.executable, REPLAY, str(path), '--play', '--rate', '0.1',
                               '--wait-subscribers', '30'],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, 'PYTHONUNBUFFERED': '1'})
    try:
        probe.wait_for(lambda: got['y'], 30, 'the first replayed sample')
        # A subscriber that joins after the weights were replayed still gets them: latched.
        late = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
        probe.node.create_subscription(NssmWeights, 'nssm_weights', got['weights'].append, late)
        try:
            probe.wait_for(lambda: len(got['y']) == 40 and got['weights'], 90, 'the replay')
        except AssertionError as err:
            raise AssertionError(f"{err}: {len(got['y'])} samples (steps "
                                 f"{[m.step for m in got['y']][:5]}...), "
                                 f"{len(got['weights'])} weights") from None
        out, err = player.communicate(timeout=30)
    finally:
        if player.poll() is None:
            player.kill()
            player.wait()
    assert player.returncode == 0, err
    assert json.loads(out.splitlines()[-1]) == {'published': {'/nssm_weights': 1, '/y': 40}}
    assert [m.step for m in got['y']] == list(range(40))
    assert [list(m.y) for m in got['y']] == [[0.5 * k, -k] for k in range(40)]
    assert got['weights'][0].version == 4 and list(got['weights'][0].params) == [1.5, -2.0]


def _by_hand_recording(path: Path, q):
    """A recording without run metadata: 20 samples on /y, /u and /mpc_status, whose
    controller weights the outputs with `q` (None: a status without weights)."""
    from mcap_ros2._dynamic import serialize_dynamic
    from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
    from metampc_recording.msg_schema import DefinitionSource
    from metampc_recording.rosbag2_qos import QosProfile
    qos = [QosProfile(history='unknown', depth=0, liveliness='automatic')]
    writer = Rosbag2McapWriter(McapWriterConfig(str(path), 4096, 'lz4', {}))
    encoders = {}
    for topic, kind in (('/y', 'PlantOutput'), ('/u', 'ControlInput'),
                        ('/mpc_status', 'MpcStatus')):
        name = f'metampc_msgs/msg/{kind}'
        writer.add_topic(topic, name, qos)
        encoders[topic] = serialize_dynamic(name, DefinitionSource().get(name).text)[name]
    t = 1_000_000_000
    for k in range(20):
        header = {'stamp': {'sec': k // 10, 'nanosec': (k % 10) * 100_000_000}, 'frame_id': ''}
        msgs = {'/y': {'header': header, 'step': k, 'y': [0.1 * k, 1.0], 'u_applied': [0.0]},
                '/u': {'header': header, 'step': k, 'u': [0.0]},
                '/mpc_status': {'header': header, 'step': k, 'solver_status': 'solved',
                                'y_ref': [1.0, 0.0] * 3, **({'q': q} if q else {})}}
        for topic, msg in msgs.items():
            t += 1_000_000
            writer.write(topic, encoders[topic](msg), t, t, k)
    writer.close()


@pytest.mark.parametrize('q, tracked', [([1.0, 0.0], [0]), ([0.0, 2.0], [1]), (None, [0, 1])])
def test_without_run_metadata_the_outputs_the_controller_weights_are_tracked(tmp_path, q,
                                                                             tracked):
    path = tmp_path / 'by_hand.mcap'
    _by_hand_recording(path, q)
    report = analyse(str(path), out_dir=str(tmp_path / 'out'), plots=False)
    assert report['metrics']['tracking']['tracked_outputs'] == tracked, report['metrics']
