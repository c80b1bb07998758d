"""The orchestrator end to end on a CI-sized configuration (config/ci.yaml), and Ctrl-C.

The report is checked against the recording read by a reader this project did not write
(`rosbags`): the tracking RMSE of each method recomputed from the raw messages, the service
results from the recorded events.
"""
import json
import math
import os
from pathlib import Path
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from metampc_bringup.experiment import run_experiment
from metampc_bringup.experiment_config import ConfigError, load
from metampc_bringup.processes import session_pids

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')
ARTEFACTS = ('config.yaml', 'report.json', 'report.md', 'fig2_meta_training.png',
             'fig3_adaptation.png', 'tracking_all_methods.png')


def _read(mcap_path: str):
    """Events and closed-loop messages of a recording, decoded by rosbags."""
    events, outputs, statuses, inputs = [], [], [], []
    with AnyReader([Path(mcap_path)]) as reader:     # types from the schemas in the file
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            name = conn.topic.rsplit('/', 1)[-1]
            if name == 'experiment_events':
                events.append(json.loads(msg.data))
            elif name in ('y', 'mpc_status', 'u'):
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                {'y': outputs, 'mpc_status': statuses, 'u': inputs}[name].append((stamp, msg))
    return events, outputs, statuses, inputs


def _rmse(outputs, statuses, start: float, end: float) -> float:
    """x1 against the first reference row of the status answering the previous step."""
    ys = {round(m.step): m.y[0] for s, m in outputs if start - 1e-6 <= s <= end + 1e-6}
    refs = {round(m.step): m.y_ref[0] for s, m in statuses if start - 1e-6 <= s <= end + 1e-6}
    err = [ys[k + 1] - r for k, r in refs.items() if k + 1 in ys]
    return float(np.sqrt(np.mean(np.square(err))))


def test_ci_experiment_produces_every_artefact_consistent_with_the_recording(tmp_path):
    out = str(tmp_path / 'run')
    config = load(CI_CONFIG)
    report = run_experiment(config, out, progress=False)
    for name in ARTEFACTS:
        assert os.path.getsize(os.path.join(out, name)) > 1000 or name.endswith('.yaml'), name
    seed_dir = os.path.join(out, 'seed_0')
    assert os.path.exists(os.path.join(seed_dir, 'report.json'))
    events, outputs, statuses, inputs = _read(os.path.join(seed_dir, 'recording.mcap'))
    per_seed = report['per_seed'][0]
    assert per_seed['complete'] and per_seed['theta'] == config.theta
    kinds = [e['event'] for e in events]
    assert kinds[0] == 'start' and kinds[-1] == 'done'
    collected = next(e for e in events if e['event'] == 'collect_end')
    assert collected['samples'] >= config.target_samples
    n = config.track_steps()
    for method in config.methods:
        start = next(e for e in events if e['event'] == 'track_start' and e['method'] == method)
        end = next(e for e in events if e['event'] == 'track_end' and e['method'] == method)
        tracking = per_seed['methods'][method]['tracking']
        assert not tracking['escaped'] and end['steps'] == n
        assert tracking['ticks']['missed'] == 0
        assert tracking['tracking']['samples'] == n       # pairs y_{k+1} with ref of step k
        # The answers of steps 0..n-1, each once (not y_n's, nor the previous run's).
        assert tracking['samples']['inputs'] == tracking['samples']['mpc_status'] == n
        assert tracking['tracking']['rmse'] == pytest.approx(
            _rmse(outputs, statuses, start['stamp'], end['stamp']), rel=1e-9, abs=1e-12)
        planners = set(tracking['planner'])
        assert planners == {'nmpc' if method == 'nmpc' else 'latent_mpc'}, planners
        if method != 'nmpc':
            adapted = next(e for e in events if e['event'] == 'adapt' and e['method'] == method)
            assert tracking['model_versions']['used_by_inputs'] == [adapted['model_version']]
            assert per_seed['methods'][method]['adapt']['loss_curve'] == adapted['loss_curve']
            assert len(adapted['loss_curve']) == config.adapt[method].get('steps', 20) + 1 \
                or method == 'oracle'
    for method in config.meta_methods():
        trained = next(e for e in events if e['event'] == 'meta_train' and e['method'] == method)
        assert len(trained['loss_curve']) == config.meta_train[method]['iterations']
        assert all(math.isfinite(v) for v in trained['loss_curve'])
    # Claims are computed from the same values.
    b0 = report['claims']['b_adaptation_order']['0']['losses'][0]
    assert b0['imaml'] == per_seed['methods']['imaml']['adapt']['loss_curve'][0]
    with open(os.path.join(out, 'report.md')) as f:
        text = f.read()
    assert '(a) final meta-training loss' in text and 'fig2_meta_training.png' in text


def _pids_in_domain(domain: int):
    """Live processes whose environment has ROS_DOMAIN_ID=domain (claimed by one run)."""
    pids = []
    for entry in filter(str.isdigit, os.listdir('/proc')):
        try:
            with open(f'/proc/{entry}/environ', 'rb') as f:
                if f'ROS_DOMAIN_ID={domain}'.encode() in f.read().split(b'\0'):
                    pids.append(int(entry))
        except OSError:
            continue
    return pids


def test_ctrl_c_stops_every_node_and_leaves_a_readable_recording(tmp_path):
    out = str(tmp_path / 'run')
    proc = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--out', out, '--no-progress', '--methods', 'imaml'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        # Interrupt once meta-training has started: every node is up then.
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if 'collect done' in line:
                break
        os.killpg(proc.pid, signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            for pid in session_pids(proc.pid):
                os.kill(pid, signal.SIGKILL)
    text = ''.join(lines) + rest
    assert proc.returncode == 130, text
    domain = int(re.search(r'ROS_DOMAIN_ID=(\d+)', text).group(1))
    assert _pids_in_domain(domain) == [], 'processes left behind'
    events, outputs, _, _ = _read(os.path.join(out, 'seed_0', 'recording.mcap'))
    assert events[0]['event'] == 'start' and len(outputs) >= 60


def test_config_errors_name_the_key(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('methods: [imaml]\nlearnr: {}\n')
    with pytest.raises(ConfigError, match='learnr'):
        load(str(bad))
    bad.write_text('meta_train: {imaml: {iterations: 3, inner_stpes: 2}}\n')
    with pytest.raises(ConfigError, match='inner_stpes'):
        load(str(bad))
    bad.write_text('plant: {dt: 0.05}\n')
    with pytest.raises(ConfigError, match='top level'):
        load(str(bad))
    with pytest.raises(ConfigError, match='methods'):
        load(None, {'methods': ['imaml', 'reptile']})
    config = load(None, {'seeds': 3, 'first_seed': 5})
    thetas = [config.target_theta(s) for s in config.seed_list()]
    assert config.seed_list() == [5, 6, 7] and len(set(thetas)) == 3
    assert thetas == [load(None).target_theta(s) for s in (5, 6, 7)]   # seeded, reproducible
