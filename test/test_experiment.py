"""The orchestrator end to end on a CI-sized configuration (config/ci.yaml), and Ctrl-C.

The report is checked against the recording read by a reader this project did not write
(`rosbags`): the tracking RMSE of each method recomputed from the raw messages, the service
results from the recorded events, a held-out target loss from the recorded weights by numpy.
"""
import contextlib
import json
import math
import os
from pathlib import Path
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from metampc_bringup.analysis.retrack import (adapted_models, controller_values, fly,
                                              retrack_seed)
from metampc_bringup.experiment import rebuild_report, run_experiment
from metampc_bringup.experiment_config import ConfigError, learner_config, load
from metampc_bringup.orchestration.lifeline import ENV as LIFELINE
from metampc_bringup.orchestration.processes import session_pids
from metampc_bringup.orchestration.procfs import pids_with_env, uptime_s
from metampc_bringup.run_folder import mark_incomplete
from metampc_learner.heldout import target_heldout
from metampc_testing import (free_port, loopback_dask, per_seed_reports, read_with_rosbags,
                             SESSION_ENV, timing_free)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CI_CONFIG = os.path.join(ROOT, 'config', 'ci.yaml')
ARTEFACTS = ('config.yaml', 'report.json', 'report.md', 'fig2_meta_training.png',
             'fig3_adaptation.png', 'tracking_all_methods.png')


def _rmse(outputs, statuses, start: float, end: float) -> float:
    """x1 against the first reference row of the status answering the previous step."""
    ys = {round(m.step): m.y[0] for s, m in outputs if start - 1e-6 <= s <= end + 1e-6}
    refs = {round(m.step): m.y_ref[0] for s, m in statuses if start - 1e-6 <= s <= end + 1e-6}
    err = [ys[k + 1] - r for k, r in refs.items() if k + 1 in ys]
    return float(np.sqrt(np.mean(np.square(err))))


def _weights(mcap_path: str, version: int):
    """The NssmWeights message of `version`, decoded by rosbags."""
    with AnyReader([Path(mcap_path)]) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic.rsplit('/', 1)[-1] == 'nssm_weights':
                msg = reader.deserialize(raw, conn.msgtype)
                if msg.version == version:
                    return msg
    raise AssertionError(f'no model version {version} recorded')


def _numpy_loss(msg, trajectories, horizon: int) -> float:
    """l_SSM of eq. (SSM) of the message's model on every window of H + T samples: encoder
    MLP and latent recursion step by step, float64, normalised units."""
    flat, offsets, p, at = np.asarray(msg.params, np.float64), list(msg.shape_offsets), {}, 0
    for i, name in enumerate(msg.names):
        shape = [int(n) for n in msg.shapes[offsets[i]:offsets[i + 1]]]
        p[name] = flat[at:at + int(np.prod(shape))].reshape(shape)
        at += int(np.prod(shape))
    n_h, layers, errors = int(msg.history), len(msg.encoder_layers) + 1, []
    for t in trajectories:
        u, y = (t.u - msg.u_mean) / msg.u_std, (t.y - msg.y_mean) / msg.y_std
        for s in range(len(t) - n_h - horizon + 1):
            z = np.concatenate([u[s:s + n_h], y[s:s + n_h]], axis=1).reshape(-1)
            for i in range(layers):
                z = p[f'encoder.{i}.weight'] @ z + p[f'encoder.{i}.bias']
                z = np.maximum(z, 0.0) if i < layers - 1 else z
            error = 0.0
            for k in range(s + n_h, s + n_h + horizon):
                z = p['A'] @ z + p['B'] @ u[k]
                error += np.sum(np.square(p['C'] @ z - y[k]))
            errors.append(error / horizon)
    return float(np.mean(errors))


def test_ci_experiment_produces_every_artefact_consistent_with_the_recording(tmp_path):
    out = str(tmp_path / 'run')
    config = load(CI_CONFIG)
    report = run_experiment(config, out, progress=False)
    for name in ARTEFACTS:
        assert os.path.getsize(os.path.join(out, name)) > 1000 or name.endswith('.yaml'), name
    seed_dir = os.path.join(out, 'seed_0')
    assert os.path.exists(os.path.join(seed_dir, 'report.json'))
    events, outputs, statuses, inputs = read_with_rosbags(os.path.join(seed_dir, 'recording.mcap'))
    per_seed = report['per_seed'][0]
    assert per_seed['complete'] and per_seed['theta'] == [config.theta] == [0.5]
    kinds = [e['event'] for e in events]
    assert kinds[0] == 'start' and kinds[-1] == 'done'
    # The NMPC tracked while the first meta-model trained (its answer came after).
    nmpc_end = next(i for i, e in enumerate(events)
                    if e['event'] == 'track_end' and e['method'] == 'nmpc')
    assert kinds.index('collect_end') < nmpc_end < kinds.index('meta_train'), kinds
    collected = next(e for e in events if e['event'] == 'collect_end')
    assert collected['samples'] >= config.target_samples
    # The learner's D_target holds the collection whole: nothing lost between plant and learner.
    held = next(e for e in events if e['event'] == 'buffering_stopped')
    assert (held['kept'], held['lost']) == (config.target_samples, 0), held
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
            if method == 'arx':       # no steps: its l_SSM after the least-squares fit
                assert len(adapted['loss_curve']) == 1
            elif method != 'oracle':
                assert len(adapted['loss_curve']) == config.adapt[method].get('steps', 20) + 1
    for method in config.meta_methods():
        trained = next(e for e in events if e['event'] == 'meta_train' and e['method'] == method)
        assert len(trained['loss_curve']) == config.meta_train[method]['iterations']
        assert all(math.isfinite(v) for v in trained['loss_curve'])
    # Claims are computed from the same values.
    b0 = report['claims']['b_adaptation_order']['0']['losses'][0]
    # Every published model scored on >= 2000 fresh samples of theta*; iMAML's adapted loss
    # by numpy from the recorded weights, on the set rebuilt from the learner's settings (the
    # CI plant has the learner's dt, substeps, bounds and box).
    assert per_seed['heldout']['samples'] >= 2000
    for method in config.methods:
        entry = per_seed['methods'][method].get('heldout')
        assert (entry is None) == (method == 'nmpc'), method
        if entry:
            assert entry['samples'] >= 2000 and math.isfinite(entry['adapted']), method
            meta = method in config.meta_methods()
            assert (entry['meta'] is not None) == meta and (not meta or entry['meta'] > 0)
    learner = learner_config(config, per_seed['seed'])
    version = per_seed['methods']['imaml']['adapt']['model_version']
    assert per_seed['methods']['imaml']['heldout']['adapted'] == pytest.approx(_numpy_loss(
        _weights(os.path.join(seed_dir, 'recording.mcap'), version),
        target_heldout(config.theta, learner.source, per_seed['seed']),
        learner.nssm.loss_horizon), rel=1e-4)
    assert b0['imaml'] == per_seed['methods']['imaml']['adapt']['loss_curve'][0]
    # The same tracking runs in one process (closed_loop, no ROS) give the same costs: the
    # lockstep graph adds nothing and loses nothing (scripts/retrack.py's premise).
    again = retrack_seed(config, per_seed['seed'], os.path.join(seed_dir, 'recording.mcap'), {})
    assert set(again) == set(config.methods)
    for method, result in again.items():
        recorded = per_seed['methods'][method]['tracking']['tracking']['cost']
        assert result.cost == pytest.approx(recorded, rel=1e-9, abs=1e-12), method
    # scripts/retrack.py with the yardstick's own settings (--nmpc): every ratio is against
    # that NMPC, flown again (not the recorded one), here with a tail of 3 samples.
    retrack = [sys.executable, os.path.join(ROOT, 'scripts', 'retrack.py'), out]
    subprocess.run(retrack + ['--nmpc', 'nmpc_tail=3', '--variant', 'a:', '--seeds',
                              str(per_seed['seed'])], check=True, timeout=300)
    for seeds, error in (('99', f'--seeds: {out} has no seed [99]'),
                         ('1,x', "'1,x' is not seeds separated by commas")):
        bad = subprocess.run(retrack + ['--seeds', seeds], capture_output=True, text=True,
                             timeout=120)
        assert bad.returncode == 2 and error in bad.stderr, bad.stderr
    with open(os.path.join(out, 'retrack.json')) as f:
        table = json.load(f)['summary']['a']
    cfg = config.resolved()
    seed = per_seed['seed']
    tailed = fly(controller_values(cfg, seed, {'nmpc_tail': 3}),
                 cfg.node_parameters('plant', seed), cfg.target_theta(seed), cfg.track_x0,
                 cfg.track_steps()).tracking_cost(list(cfg.tracked_outputs))
    assert tailed != again['nmpc'].cost
    for method in config.meta_methods():
        assert table[method]['ratios'][str(seed)] == pytest.approx(
            again[method].cost / tailed, rel=1e-9), method
    # scripts/model_gains.py reads the same run: a row per adapted model, its cost ratio the
    # report's (the gains themselves: test_model_gains.py against closed forms).
    gains = subprocess.run([sys.executable, os.path.join(ROOT, 'scripts', 'model_gains.py'), out],
                           capture_output=True, text=True, timeout=300, check=True).stdout
    row = next(line for line in gains.splitlines() if line.startswith(f'{seed} | imaml | '))
    assert float(row.split(' | ')[2]) == pytest.approx(
        again['imaml'].cost / again['nmpc'].cost, abs=0.006), row
    with open(os.path.join(out, 'report.md')) as f:
        text = f.read()
    assert '(a) final meta-training loss' in text and 'fig2_meta_training.png' in text
    assert '## Held-out target loss on 2000 independent samples' in text
    # The reports again from the recordings alone: the same claims and wall time.
    rebuilt = rebuild_report(out)
    assert rebuilt['claims'] == report['claims']
    assert rebuilt['wall_time_s'] == pytest.approx(report['wall_time_s'])
    # A folder assembled from seed folders (no report.json of its own): no wall time to give.
    os.remove(os.path.join(out, 'report.json'))
    assert rebuild_report(out)['claims'] == report['claims']
    with open(os.path.join(out, 'report.md')) as f:
        assert 'Wall time: not recorded (report rebuilt from the recordings).' in f.read()
    # A seed's folder marked incomplete (an interrupted try; here a copy) is no finished seed.
    shutil.copytree(seed_dir, os.path.join(out, 'seed_7'))
    mark_incomplete(os.path.join(out, 'seed_7'), 'interrupted')
    assert [s['seed'] for s in rebuild_report(out)['per_seed']] == [per_seed['seed']]


def _pids_in_domain(domain: int, started_before: float = math.inf):
    """Live processes of this test session whose environment has ROS_DOMAIN_ID=domain
    (claimed by one run) and that started before `started_before` (s since boot). A run gives
    its domain back as its processes end, and another test session on the machine (the other
    xdist worker) may claim it at once, before the run's own end is noted: its processes are
    not the run's leftovers."""
    return pids_with_env({'ROS_DOMAIN_ID': str(domain), SESSION_ENV: os.environ[SESSION_ENV]},
                         started_before)


def _interrupt_after_collection(args, collections: int, timeout: float,
                                signum: int = signal.SIGINT):
    """Run run_experiment.py on the CI config with `args`, SIGINT its process group (as
    Ctrl-C does; `signum` SIGTERM: the process alone, as a process manager does) once
    `collections` seeds have collected; (exit status, everything it printed)."""
    proc = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--no-progress', *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if sum('collect done' in x for x in lines) == collections:
                break
        if signum == signal.SIGINT:
            os.killpg(proc.pid, signum)
        else:
            os.kill(proc.pid, signum)
        rest, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            for pid in session_pids(proc):
                os.kill(pid, signal.SIGKILL)
    return proc.returncode, ''.join(lines) + rest


def test_both_model_classes_fly_in_one_run_each_with_its_report_rows(tmp_path):
    """config/default.yaml's form, CI-sized: one learner of the NSSM's class meta-trains and
    adapts the feature NARX (narx_*) and the paper's NSSM on the same D_target; the recorded
    weights of each row are of its class, the report scores each on the held-out set and
    compares the NARX with the ARX of its class, the adapted NARX's training loss is not
    above its ARX's, and the same tracking in one process (retrack, by the report's names)
    gives the recorded costs."""
    base = load(CI_CONFIG)
    learner = {**base.learner, 'narx_features': 8, 'narx_hidden': [16],
               'narx_iterations': 20, 'narx_batch_size': 4, 'narx_windows': 16}
    config = load(CI_CONFIG, {'methods': ['narx_imaml', 'narx_arx', 'imaml', 'arx', 'nmpc'],
                              'learner': learner})
    out = str(tmp_path / 'run')
    report = run_experiment(config, out, progress=False)
    per_seed = report['per_seed'][0]
    assert per_seed['complete']
    mcap = os.path.join(out, 'seed_0', 'recording.mcap')
    for method in config.methods:
        tracking = per_seed['methods'][method]['tracking']
        assert not tracking['escaped'] and tracking['steps'] == config.track_steps(), method
        assert set(tracking['planner']) == {'nmpc' if method == 'nmpc' else 'latent_mpc'}
    models = {m: _weights(mcap, per_seed['methods'][m]['adapt']['model_version'])
              for m in ('narx_imaml', 'narx_arx', 'imaml', 'arx')}
    assert {m: (w.model_class, w.method) for m, w in models.items()} == {
        'narx_imaml': ('feature_narx', 'imaml'), 'narx_arx': ('feature_narx', 'arx'),
        'imaml': ('nssm', 'imaml'), 'arx': ('nssm', 'arx')}
    assert models['narx_imaml'].features == 8 and models['imaml'].history == 10
    assert models['narx_imaml'].train_loss <= models['narx_arx'].train_loss * (1 + 1e-9)
    for method in ('narx_imaml', 'narx_arx', 'imaml', 'arx'):
        assert math.isfinite(per_seed['methods'][method]['heldout']['adapted']), method
    held = report['claims']['b_heldout_large']['adapted']['stats']
    assert set(held) == {'imaml<arx', 'narx_imaml<narx_arx'}
    costs = report['claims']['c_tracking_cost_stats']
    assert {'narx_imaml<narx_arx', 'narx_imaml<arx', 'narx_imaml<imaml', 'imaml<arx'} <= set(
        costs)
    again = retrack_seed(config, per_seed['seed'], mcap, {})
    assert set(again) == set(config.methods)
    for method, result in again.items():
        recorded = per_seed['methods'][method]['tracking']['tracking']['cost']
        assert result.cost == pytest.approx(recorded, rel=1e-9, abs=1e-12), method


def test_a_run_without_meta_training_adapts_on_the_whole_collection(tmp_path):
    """`--methods arx`: nothing trains between the collection and the first adapt, so the
    learner is asked to stop buffering while it is still taking the collection in. The stop
    waits for it (set_buffering's `least`): D_target is the whole collection, as after a
    meta-training (before 2026-12-02 such a run kept 119-300 of 300 samples)."""
    out = str(tmp_path / 'run')
    done = _run_to_end(['--out', out, '--methods', 'arx'])
    assert done.returncode == 0, done.stdout
    config = load(CI_CONFIG)
    per_seed = per_seed_reports(out)[0]
    held = per_seed['buffering']
    assert (held['kept'], held['lost']) == (config.target_samples, 0), held
    train = config.target_samples - round(learner_config(config, 0).heldout_fraction
                                          * config.target_samples)
    model = adapted_models(os.path.join(out, 'seed_0', 'recording.mcap'))['arx']
    assert model.train_samples == train


def test_ctrl_c_stops_every_node_and_leaves_a_readable_recording(tmp_path):
    out = str(tmp_path / 'run')
    # Interrupt once meta-training has started: every node is up then.
    code, text = _interrupt_after_collection(['--out', out, '--methods', 'imaml'], 1, 60)
    ended = uptime_s()
    assert code == 130, text
    domain = int(re.search(r'ROS_DOMAIN_ID=(\d+)', text).group(1))
    assert _pids_in_domain(domain, ended) == [], 'processes left behind'
    _assert_interrupted_seed(os.path.join(out, 'seed_0'))


def _assert_interrupted_seed(folder: str) -> None:
    """An interrupted seed's folder: its recording readable up to the interruption, marked
    INCOMPLETE, no report."""
    events, outputs, _, _ = read_with_rosbags(os.path.join(folder, 'recording.mcap'))
    assert events[0]['event'] == 'start' and len(outputs) >= 60
    with open(os.path.join(folder, 'INCOMPLETE')) as f:
        assert f.read().startswith('interrupted;')
    assert not os.path.exists(os.path.join(folder, 'report.json'))


def test_ctrl_c_while_the_script_imports_is_an_interruption(tmp_path):
    """SIGINT while run_experiment.py imports torch (seen in its memory map, not guessed by a
    sleep): exit 130 and the interruption line, no traceback, no process left."""
    out = tmp_path / 'run'
    proc = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--out', str(out), '--no-progress'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60.0
        while proc.poll() is None and time.monotonic() < deadline:
            with open(f'/proc/{proc.pid}/maps') as f:
                if 'libtorch' in f.read():
                    break
            time.sleep(0.005)
        os.killpg(proc.pid, signal.SIGINT)
        text = proc.communicate(timeout=60)[0]
    finally:
        if proc.poll() is None:
            for pid in session_pids(proc):
                os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130 and 'Traceback' not in text, text
    assert 'run_experiment: interrupted' in text, text
    assert session_pids(proc) == []


def test_ctrl_c_while_the_nodes_start_leaves_no_process(tmp_path):
    """SIGINT as soon as the first node of the run's domain exists, while the others start:
    exit 130 and no process left in the domain (one was, when the signal came between a
    node's fork and its registration in the process group)."""
    proc = subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--out', str(tmp_path / 'run'), '--no-progress'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            found = re.search(r'ROS_DOMAIN_ID=(\d+)', line)
            if found:
                break
        domain = int(found.group(1))
        deadline = time.monotonic() + 60.0
        while not _pids_in_domain(domain) and time.monotonic() < deadline:
            time.sleep(0.002)
        os.killpg(proc.pid, signal.SIGINT)
        text = ''.join(lines) + proc.communicate(timeout=60)[0]
        ended = uptime_s()
    finally:
        if proc.poll() is None:
            for pid in session_pids(proc):
                os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130 and 'Traceback' not in text, text
    assert _pids_in_domain(domain, ended) == [], 'processes left behind'


def _start_run(args) -> subprocess.Popen:
    """run_experiment.py on the CI config with `args`, in a session of its own."""
    return subprocess.Popen(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--no-progress', *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _read_until(proc: subprocess.Popen, pattern: str, lines: list) -> re.Match:
    """Read proc's output into `lines` until a line matches `pattern`; the match."""
    for line in proc.stdout:
        lines.append(line)
        found = re.search(pattern, line)
        if found:
            return found
    raise AssertionError(f'{pattern!r} never printed:\n' + ''.join(lines))


def _wait_domain_empty(domain: int, killed: float, timeout: float = 5.0) -> list:
    """The run's processes still in `domain` `timeout` s after `killed` (none: empty)."""
    deadline = time.monotonic() + timeout
    while _pids_in_domain(domain, killed) and time.monotonic() < deadline:
        time.sleep(0.05)
    return _pids_in_domain(domain, killed)


def _kill_leftovers(proc: subprocess.Popen, domains, killed: float) -> None:
    """After a failed assertion: nothing of the run may outlive the test (its session, its
    domains' nodes, its seed children: their ROS_DOMAIN_ID is not in their /proc environ).

    Only processes that started before `killed` (s since boot: the kill, or now if it never
    came): until then the run held its domains, so nobody else's process can be in them; once
    its nodes are gone another test session may claim a domain, and its processes are not
    ours to kill (measured: a recorder of a second suite SIGKILLed at start-up)."""
    children = _seed_children(killed)
    nodes = [p for d in domains for p in _pids_in_domain(d, killed)]
    for pid in session_pids(proc) + children + nodes:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    proc.wait()


def test_sigkill_during_meta_training_leaves_no_process(tmp_path):
    """run_experiment.py killed by SIGKILL while the learner meta-trains (no handler of its
    runs): its `ros2 run` wrappers and nodes end within 5 s
    (metampc_bringup.orchestration.lifeline)."""
    out = str(tmp_path / 'run')
    proc = _start_run(['--out', out, '--methods', 'imaml'])
    lines, domains, killed = [], [], None
    try:
        domains.append(int(_read_until(proc, r'ROS_DOMAIN_ID=(\d+)', lines).group(1)))
        _read_until(proc, r'collect done', lines)     # meta_train is the next call
        assert len(_pids_in_domain(domains[0])) >= 8, 'the nodes are up'
        os.kill(proc.pid, signal.SIGKILL)
        killed = uptime_s()
        proc.wait()
        assert _wait_domain_empty(domains[0], killed) == [], 'processes left behind'
    finally:
        _kill_leftovers(proc, domains, killed if killed is not None else uptime_s())
        proc.stdout.close()


def test_sigkill_of_a_seed_child_leaves_no_process_of_its_seed(tmp_path):
    """--jobs 2: one seed's child killed by SIGKILL: its nodes end within 5 s; the other seed
    runs to its end, and the run fails naming the killed seed (its folder marked INCOMPLETE),
    with nothing left running."""
    out = str(tmp_path / 'run')
    proc = _start_run(['--out', out, '--methods', 'imaml', '--seeds', '2', '--jobs', '2'])
    lines, domains, killed = [], {}, None
    try:
        while len(domains) < 2:
            found = _read_until(proc, r'seed (\d): ROS_DOMAIN_ID=(\d+)', lines)
            domains[int(found.group(1))] = int(found.group(2))
        _read_until(proc, r'seed 0: collect done', lines)
        child = [pid for pid in _seed_children(killed=uptime_s()) if _cmdline(pid)[-1] == '0']
        assert len(child) == 1, child
        os.kill(child[0], signal.SIGKILL)
        killed = uptime_s()
        assert _wait_domain_empty(domains[0], killed) == [], 'processes left behind'
        text = ''.join(lines) + proc.communicate(timeout=300)[0]
        ended = uptime_s()
        assert proc.returncode == 1 and 'seed 0 (exit status -9' in text, text
        assert 'seed 0 failed (exit status -9); its last lines:' in text, text
        assert 'seed 1: done' in text, text
        assert _pids_in_domain(domains[1], ended) == [], 'processes left behind'
        with open(os.path.join(out, 'seed_0', 'INCOMPLETE')) as f:
            assert f.read().startswith('failed (exit status -9);')
    finally:
        _kill_leftovers(proc, domains.values(), killed if killed is not None else uptime_s())
        proc.stdout.close()


def _seed_children(killed: float) -> list:
    """This session's seed children that started before `killed` (s since boot): the test's
    own, since a session runs one test at a time."""
    return [pid for pid in pids_with_env({SESSION_ENV: os.environ[SESSION_ENV]}, killed)
            if 'metampc_bringup.orchestration.seed_jobs' in _cmdline(pid)]


def _cmdline(pid: int) -> list:
    try:
        with open(f'/proc/{pid}/cmdline', 'rb') as f:
            return f.read().decode(errors='replace').split('\0')[:-1]
    except OSError:
        return []


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
    bad.write_text('learner: {lr_outr: 0.01}\n')     # ROS would ignore it: refused here
    with pytest.raises(ConfigError, match=r'learner: unknown parameter\(s\) lr_outr'):
        load(str(bad))
    bad.write_text('controller: {horizon: 0}\n')
    with pytest.raises(ConfigError, match='controller: horizon must be >= 1, got 0'):
        load(str(bad))
    with pytest.raises(ConfigError, match='methods'):
        load(None, {'methods': ['imaml', 'reptile']})
    # Family facts, checked as the plant node checks them, before anything starts.
    with pytest.raises(ConfigError, match='theta of family duffing needs 3'):
        load(None, {'family': 'duffing', 'theta': [0.1]})
    with pytest.raises(ConfigError, match='collect_x0: x0 of family quadruple_tank needs 4'):
        load(None, {'family': 'quadruple_tank', 'collect_x0': [0.5, 0.0]})
    with pytest.raises(ConfigError, match='outside those of family pendulum'):
        load(None, {'family': 'pendulum', 'u_max': 5.0})
    config = load(None, {'seeds': 3, 'first_seed': 5})
    thetas = [tuple(config.target_theta(s)) for s in config.seed_list()]
    assert config.seed_list() == [5, 6, 7] and len(set(thetas)) == 3
    assert thetas == [tuple(load(None).target_theta(s)) for s in (5, 6, 7)]   # seeded


PARALLEL = ['--methods', 'maml', '--seeds', '2', '--jobs', '2']


def _run_to_end(args, timeout: float = 400) -> subprocess.CompletedProcess:
    """run_experiment.py on the CI config with `args`, to its end."""
    return subprocess.run(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--no-progress', *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, timeout=timeout)


@pytest.fixture(scope='module')
def parallel_run(tmp_path_factory):
    """Two seeds at once on the embedded cluster (--jobs 2); (run folder, its output)."""
    out = str(tmp_path_factory.mktemp('parallel') / 'run')
    done = _run_to_end(['--out', out, *PARALLEL])
    assert done.returncode == 0, done.stdout
    return out, done.stdout


def test_jobs_2_gives_the_per_seed_results_of_jobs_1(parallel_run, tmp_path):
    """Two seeds at once (run_experiment.py --jobs 2: an embedded dask cluster of two workers
    on loopback, a child process and a ROS domain per seed, the seed folders sent back) give,
    seed for seed, the results of the one-process run (lockstep is deterministic); the merged
    report covers both seeds."""
    out, text = parallel_run
    assert 'embedded cluster: 2 worker(s) on 127.0.0.1' in text, text
    domains = set(re.findall(r'seed \d: ROS_DOMAIN_ID=(\d+)', text))
    assert len(domains) == 2, text
    serial = run_experiment(load(CI_CONFIG, {'methods': ['maml'], 'first_seed': 1}),
                            str(tmp_path / 'serial'), progress=False)
    merged = per_seed_reports(out)
    assert [s['seed'] for s in merged] == [0, 1]
    assert merged[1]['recording'] == os.path.join(out, 'seed_1', 'recording.mcap')
    parallel_1 = timing_free(merged[1])
    assert parallel_1 == timing_free(serial['per_seed'][0])
    for run in (merged[1], serial['per_seed'][0]):
        assert (run['buffering']['kept'], run['buffering']['lost']) == (120, 0), run['buffering']
    assert parallel_1['methods']['maml']['tracking']['tracking']['rmse'] > 0


def test_the_same_command_resumes_running_only_the_seeds_without_a_report(
        parallel_run, tmp_path):
    """A copy of the two-seed run with seed 0's report gone (as if stopped before it landed):
    the same command runs seed 0 alone, leaves seed 1's folder untouched, and the merged
    report equals the uninterrupted one; a command of another configuration is refused."""
    out = str(tmp_path / 'run')
    shutil.copytree(parallel_run[0], out)
    os.remove(os.path.join(out, 'seed_0', 'report.json'))
    kept = os.stat(os.path.join(out, 'seed_1', 'recording.mcap'))
    done = _run_to_end(['--out', out, *PARALLEL])
    assert done.returncode == 0, done.stdout
    assert f'resuming {out}: 1 of 2 seeds done; running 1: 0' in done.stdout, done.stdout
    assert re.findall(r'seed (\d): ROS_DOMAIN_ID', done.stdout) == ['0'], done.stdout
    now = os.stat(os.path.join(out, 'seed_1', 'recording.mcap'))
    assert (now.st_ino, now.st_mtime_ns) == (kept.st_ino, kept.st_mtime_ns)
    assert [timing_free(s) for s in per_seed_reports(out)] == \
        [timing_free(s) for s in per_seed_reports(parallel_run[0])]
    other = _run_to_end(['--out', out, '--methods', 'maml', '--seeds', '3', '--jobs', '2'])
    assert other.returncode == 2 and 'another configuration' in other.stdout, other.stdout
    assert len(other.stdout.strip().splitlines()) == 1, other.stdout


def test_a_worker_killed_in_the_middle_of_a_seed_runs_it_again_with_the_same_results(
        parallel_run, tmp_path):
    """`dask scheduler` and a `dask worker` of two one-slot processes, started here on
    loopback, run_experiment.py --scheduler on it: the seeds run on that worker (their lines
    are in its log, not the client's). The worker process of seed 0 SIGKILLed once that seed
    has collected: the seed's nodes end with it, the scheduler runs seed 0 again, the run ends
    0 and the merged report equals, seed for seed, the embedded cluster's."""
    log = tmp_path / 'worker.log'
    with loopback_dask(log, workers=2) as (address, _):
        proc = subprocess.Popen(
            [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
             CI_CONFIG, '--no-progress', '--out', str(tmp_path / 'run'), '--scheduler',
             address, *PARALLEL[:-2]], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True)
        try:
            deadline = time.monotonic() + 300
            while 'seed 0: collect done' not in log.read_text():
                assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
                time.sleep(0.1)
            domain = int(re.search(r'seed 0: ROS_DOMAIN_ID=(\d+)', log.read_text()).group(1))
            child, = [p for p in _seed_children(uptime_s()) if _cmdline(p)[-1] == '0']
            with open(f'/proc/{child}/environ', 'rb') as f:
                worker, = [int(v[len(LIFELINE) + 1:]) for v in f.read().decode().split('\0')
                           if v.startswith(f'{LIFELINE}=')]
            os.kill(worker, signal.SIGKILL)
            killed = uptime_s()
            assert _wait_domain_empty(domain, killed, 30.0) == [], 'seed 0 left processes'
            text = proc.communicate(timeout=600)[0]
        finally:
            if proc.poll() is None:
                for pid in session_pids(proc):
                    os.kill(pid, signal.SIGKILL)
            proc.stdout.close()
    assert proc.returncode == 0, text
    assert f'cluster {address}: 2 worker(s), 2 slot(s)' in text, text
    assert 'ROS_DOMAIN_ID' not in text, text
    assert len(re.findall(r'seed 0: ROS_DOMAIN_ID', log.read_text())) == 2, log.read_text()
    assert len(re.findall(r'seed 1: ROS_DOMAIN_ID', log.read_text())) == 1, log.read_text()
    assert [timing_free(s) for s in per_seed_reports(str(tmp_path / 'run'))] == \
        [timing_free(s) for s in per_seed_reports(parallel_run[0])]


def test_ctrl_c_with_jobs_2_keeps_both_partial_seeds_and_the_same_command_resumes(tmp_path):
    """Ctrl-C (SIGINT to the process group, workers included, as a terminal sends it) while
    two seeds run on the embedded cluster: exit 130 and the interruption line, no traceback,
    no process left in either seed's domain, both seeds' folders in --out as with one process
    (recording readable, marked INCOMPLETE); the same command runs both seeds again and keeps
    the interrupted tries in incomplete/."""
    out = str(tmp_path / 'run')
    args = ['--out', out, '--methods', 'imaml', '--seeds', '2', '--jobs', '2']
    code, text = _interrupt_after_collection(args, 2, 300)
    ended = uptime_s()
    assert code == 130 and 'Traceback' not in text, text
    assert f'run_experiment: interrupted; nodes stopped, recordings in {out}' in text, text
    # By seed: a seed that failed has its last lines, its domain's among them, echoed.
    domains = dict(re.findall(r'seed (\d): ROS_DOMAIN_ID=(\d+)', text)).values()
    domains = [int(d) for d in domains]
    assert len(domains) == 2, text
    for domain in domains:
        assert _pids_in_domain(domain, ended) == [], f'processes left behind in domain {domain}'
    assert sorted(os.listdir(out)) == ['config.yaml', 'seed_0', 'seed_1'], os.listdir(out)
    for seed in (0, 1):
        _assert_interrupted_seed(os.path.join(out, f'seed_{seed}'))
    done = _run_to_end(args)
    assert done.returncode == 0, done.stdout
    assert f'resuming {out}: 0 of 2 seeds done; running 2: 0, 1' in done.stdout, done.stdout
    assert [s['seed'] for s in per_seed_reports(out)] == [0, 1]
    for seed in (0, 1):
        _assert_interrupted_seed(os.path.join(out, 'incomplete', f'seed_{seed}.1'))


def test_sigterm_with_jobs_2_is_an_interruption_too(tmp_path):
    """SIGTERM to run_experiment.py alone while two seeds run on the embedded cluster: as
    Ctrl-C, exit 130, both seeds' partial folders in --out marked INCOMPLETE, no process left
    in either seed's domain."""
    out = str(tmp_path / 'run')
    code, text = _interrupt_after_collection(
        ['--out', out, '--methods', 'imaml', '--seeds', '2', '--jobs', '2'], 2, 300,
        signal.SIGTERM)
    ended = uptime_s()
    assert code == 130 and 'Traceback' not in text, text
    # By seed: a seed that failed has its last lines, its domain's among them, echoed.
    domains = dict(re.findall(r'seed (\d): ROS_DOMAIN_ID=(\d+)', text)).values()
    domains = [int(d) for d in domains]
    assert len(domains) == 2, text
    for domain in domains:
        assert _wait_domain_empty(domain, ended, 30.0) == [], f'processes left in {domain}'
    for seed in (0, 1):
        _assert_interrupted_seed(os.path.join(out, f'seed_{seed}'))


def test_the_scheduler_gone_is_one_line_and_the_same_command_resumes(parallel_run, tmp_path):
    """A loopback `dask scheduler` SIGKILLed once seed 0 of two (one worker slot) has landed:
    run_experiment.py --scheduler says so in one line and exits 1, no traceback; seed 0 stays
    done in --out and seed 1's process ends with its worker; with a new scheduler on the same
    address the same command runs seed 1 alone, and the merged report equals the embedded
    cluster's."""
    port = free_port()
    out = str(tmp_path / 'run')
    args = [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
            CI_CONFIG, '--no-progress', '--out', out, '--methods', 'maml', '--seeds', '2',
            '--scheduler', f'tcp://127.0.0.1:{port}']
    with loopback_dask(tmp_path / 'worker.log', port=port) as (address, (scheduler, worker)):
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, start_new_session=True)
        try:
            lines = []
            _read_until(proc, r'seed 0: done', lines)
            os.killpg(scheduler.pid, signal.SIGKILL)
            text = ''.join(lines) + proc.communicate(timeout=300)[0]
        finally:
            if proc.poll() is None:
                for pid in session_pids(proc):
                    os.kill(pid, signal.SIGKILL)
            proc.stdout.close()
        assert proc.returncode == 1 and 'Traceback' not in text, text
        # The status line that follows a landed seed (cluster.run_jobs asks the scheduler for
        # it) is printed when that query beats the kill.
        after = [line for line in text[text.index('seed 0: done'):].splitlines()[1:]
                 if not re.fullmatch(r'\d\d:\d\d:\d\d seeds: 1 of 2 done \(0 failed\); .*', line)]
        assert after == [f'run_experiment: lost the scheduler {address}: 1 of 2 seeds '
                         f'finished in {out}; the same command runs the others'], text
        worker.wait(120)        # it closes without its scheduler; its seed's nodes end with it
        domains = re.findall(r'seed 1: ROS_DOMAIN_ID=(\d+)',
                             (tmp_path / 'worker.log').read_text())
        ended = uptime_s()
        for domain in domains:
            assert _wait_domain_empty(int(domain), ended, 30.0) == [], 'seed 1 left processes'
    assert os.path.isfile(os.path.join(out, 'seed_0', 'report.json'))
    with loopback_dask(tmp_path / 'again.log', port=port):
        done = _run_to_end(args[5:])
    assert done.returncode == 0, done.stdout
    assert f'resuming {out}: 1 of 2 seeds done; running 1: 1' in done.stdout, done.stdout
    assert [timing_free(s) for s in per_seed_reports(out)] == \
        [timing_free(s) for s in per_seed_reports(parallel_run[0])]


def test_jobs_beyond_the_cores_is_refused(tmp_path):
    out = tmp_path / 'run'
    done = subprocess.run(
        [sys.executable, os.path.join(ROOT, 'scripts', 'run_experiment.py'), '--config',
         CI_CONFIG, '--out', str(out), '--seeds', '2', '--jobs', str(os.cpu_count() + 1)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    assert done.returncode == 2 and 'usable cores' in done.stdout, done.stdout
    assert len(done.stdout.strip().splitlines()) == 1 and not out.exists()
