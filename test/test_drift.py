"""Scenario drift end to end on a CI-sized configuration (config/ci_drift.yaml), twice.

Checked against the recording read by `rosbags` (a reader this project did not write): the
plant's theta steps at the schedule's exact step in every run but the constant ones; every
adaptation request is answered by a model used from exactly swap_delay steps later, or by a
refusal of the model check (the model in use stays, model_status says why) (lockstep:
the answer of that step waited for it); 'none' runs ask nothing; periodic requests fall at the
periods; and a second run of the same seed makes the same requests, swaps and inputs.
"""
import os

import pytest
import yaml

from metampc_bringup.experiment import run_experiment
from metampc_bringup.experiment_config import ConfigError, load
from metampc_testing import read_with_rosbags

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(ROOT, 'config', 'ci_drift.yaml')
SWAP_DELAY = 10     # the controller's default
TRIAL = 20          # controller.model_check_trial of ci_drift


def runs_of(mcap_path: str):
    """Per run name: its outputs, statuses and inputs, decoded by rosbags and cut by the
    events' stamps (answers stamped with the run's last y are not the run's)."""
    events, outputs, statuses, inputs = read_with_rosbags(mcap_path)
    msgs = [(name, stamp, msg) for name, rows in (('y', outputs), ('mpc_status', statuses),
                                                  ('u', inputs)) for stamp, msg in rows]
    starts = {e['run']: e for e in events if e['event'] == 'track_start'}
    out = {}
    for e in events:
        if e['event'] != 'track_end':
            continue
        lo, hi = starts[e['run']]['stamp'] - 1e-6, e['stamp'] + 1e-6
        run = {'y': [], 'mpc_status': [], 'u': []}
        for name, stamp, msg in msgs:
            if lo <= stamp <= hi and not (name != 'y' and stamp > hi - 2e-6):
                run[name].append(msg)
        out[e['run']] = run
    return out


@pytest.fixture(scope='module')
def two_runs(tmp_path_factory):
    config = load(CONFIG)
    reports = []
    for i in range(2):
        out = str(tmp_path_factory.mktemp(f'drift{i}'))
        reports.append((out, run_experiment(config, os.path.join(out, 'run'), progress=False)))
    return config, reports


def test_requests_swaps_and_theta_steps_are_where_the_rules_put_them(two_runs):
    config, ((out, report), _) = two_runs
    drift = config.drift_config()
    runs = runs_of(os.path.join(out, 'run', 'seed_0', 'recording.mcap'))
    assert set(runs) == {'nmpc'} | {f'{m}/{mode}' for m in drift.methods
                                    for mode in (*drift.modes, 'constant')}
    change = int(round(drift.schedule[0] / config.dt))
    theta0 = config.target_theta(0)[0]
    for name, run in runs.items():
        thetas = {m.step: m.theta[0] for m in run['y']}
        n = max(thetas)
        assert n == int(round(drift.duration / config.dt)), name
        want = theta0 if name.endswith('/constant') else theta0 - 1.0
        assert thetas[change - 1] == theta0 and thetas[change] == want, name
        requests = [m.step for m in run['mpc_status'] if m.adapt_request]
        versions = {m.step: m.model_version for m in run['mpc_status']}
        swaps = [k for k in sorted(versions)[1:] if versions[k] != versions[k - 1]]
        if name == 'nmpc' or name.endswith('/none'):
            assert requests == [] and swaps == [], name
            continue
        # Each request's answer tried from exactly request + swap_delay and in use after its
        # trial (within the run), or refused by the model check at its trial's end or at
        # arrival (the model in use stays and a model event says why).
        refused = {m.step for m in run['mpc_status'] for e in m.model_events
                   if (e.outcome, e.cause) == ('refused', 'check')}
        answered = [k + SWAP_DELAY + TRIAL for k in requests if k + SWAP_DELAY + TRIAL < n]
        assert set(swaps) <= set(answered), name
        for k in set(answered) - set(swaps):
            assert any(j in refused for j in range(k - SWAP_DELAY - TRIAL, n)), (name, k)
        if name.endswith('/periodic'):
            period = int(round(4.0 / config.dt))     # controller.adapt_period of ci_drift
            assert requests == list(range(period, n, period)), name
        # Every request of a triggered run comes after the baseline (2 s) of its model.
        if name.endswith('/triggered') or name.endswith('/constant'):
            assert all(k >= int(round(2.0 / config.dt)) for k in requests), name
    table = report['table']
    assert set(table) == {f'{m}/{mode}' for m in drift.methods
                          for mode in (*drift.modes, 'constant')}
    assert all(row['adaptations'] == [0] for name, row in table.items()
               if name.endswith('/none'))
    assert os.path.exists(os.path.join(out, 'run', 'seed_0', 'drift_imaml.png'))
    assert 'recovery, median (worst)' in open(os.path.join(out, 'run', 'report.md')).read()


def test_the_same_seed_makes_the_same_requests_swaps_and_inputs(two_runs):
    _, ((first, _), (second, _)) = two_runs
    a = runs_of(os.path.join(first, 'run', 'seed_0', 'recording.mcap'))
    b = runs_of(os.path.join(second, 'run', 'seed_0', 'recording.mcap'))
    assert set(a) == set(b)
    for name in a:
        for topic in ('mpc_status', 'u'):
            key = (lambda m: (m.step, m.adapt_request, m.model_version)) if topic == \
                'mpc_status' else (lambda m: (m.step, tuple(m.u)))
            assert [key(m) for m in a[name][topic]] == [key(m) for m in b[name][topic]], name


@pytest.mark.parametrize('drift, match', [
    ({'schedule': [6.0, 6.0, -9.0]}, r'theta = -8.5 lies outside the range \[-4, 4\]'),
    ({'modes': ['sometimes']}, 'drift.modes'),
    ({'methods': ['oracle']}, 'drift.methods'),
    ({'durations': 3}, 'drift: unknown key'),
])
def test_bad_drift_settings_are_one_clear_error(tmp_path, drift, match):
    with open(CONFIG) as f:
        base = yaml.safe_load(f)['drift']
    with pytest.raises(ConfigError, match=match):
        load(CONFIG, {'drift': {**base, **drift}})
