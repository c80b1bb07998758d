"""A plant family from a package outside this project (examples/mass_spring_friction), installed
with pip, is found by name by the nodes and by the experiment, without a change here.

The package is installed with `pip install --target` into a folder of the test session, which
goes on PYTHONPATH (for the nodes) and sys.path (for the in-process experiment): nothing in
the shared environment changes.
"""
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.integrate import solve_ivp

from metampc_bringup.experiment import run_experiment
from metampc_bringup.experiment_config import load

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLE = os.path.join(ROOT, 'examples', 'mass_spring_friction')
THETA = [1.2, 1.5, 0.1]      # m (kg), k (N/m), mu (N)
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def spring(x, f, theta):
    """The example's equations, written out again from its docstring."""
    m, k, mu = theta
    return [x[1], (-k * x[0] - 0.1 * x[1] - mu * math.tanh(x[1] / 0.05) + f) / m]


@pytest.fixture(scope='module')
def user_site(tmp_path_factory):
    """The example installed by pip into a folder of its own (no index, no build isolation:
    the environment's setuptools builds it offline)."""
    target = str(tmp_path_factory.mktemp('user_site'))
    # Built from a copy: pip builds in the source tree, and the checkout keeps no build/ or
    # egg-info of a test's.
    source = shutil.copytree(EXAMPLE, tmp_path_factory.mktemp('example') / 'example')
    done = subprocess.run([sys.executable, '-m', 'pip', 'install', '-q', '--no-deps',
                           '--no-index', '--no-build-isolation', '--disable-pip-version-check',
                           '--target', target, str(source)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    return target


@pytest.fixture
def with_user_site(user_site, monkeypatch):
    """The installed example visible to this process and to every process it starts."""
    monkeypatch.setenv('PYTHONPATH', user_site + os.pathsep + os.environ.get('PYTHONPATH', ''))
    monkeypatch.syspath_prepend(user_site)
    return user_site


def test_listed_by_name_in_a_fresh_process(user_site):
    out = subprocess.run(
        [sys.executable, '-c', 'from metampc_plant.registry import family_names; '
         'print(",".join(family_names()))'], capture_output=True, text=True, check=True,
        env={**os.environ, 'PYTHONPATH': user_site + os.pathsep + os.environ['PYTHONPATH']})
    assert 'mass_spring_friction' in out.stdout.strip().split(','), out.stdout
    assert 'vanderpol' in out.stdout


def test_the_plant_node_simulates_it_in_lockstep(procs, probe, with_user_site):
    """The plant node with -p family:=mass_spring_friction, answered with a known input
    sequence, against scipy of the equations above: every one-step error below 1e-6."""
    from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput
    n = 30
    forces = np.repeat(np.random.default_rng(2).uniform(-2.0, 2.0, n // 5), 5)
    ys, infos = [], []
    pub = probe.node.create_publisher(ControlInput, 'u', RELIABLE)

    def on_y(msg):
        ys.append(msg)
        if msg.step < n:
            pub.publish(ControlInput(step=msg.step, u=[float(forces[msg.step])]))
    probe.node.create_subscription(PlantOutput, 'y', on_y, RELIABLE)
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    proc = procs.start('metampc_plant', 'plant', params={
        'family': 'mass_spring_friction', 'theta': THETA, 'x0': [0.3, 0.0],
        'input_timeout': 30.0})
    probe.wait_for(lambda: len(ys) > n and infos, 60.0, f'{n} answered steps')
    info = infos[-1]
    assert (info.family, list(info.theta), list(info.input_names), list(info.input_units)) == (
        'mass_spring_friction', THETA, ['f'], ['N'])
    worst = 0.0
    for k in range(n):
        sol = solve_ivp(lambda _t, z: spring(z, forces[k], THETA), (0.0, 0.1), list(ys[k].y),
                        method='DOP853', rtol=1e-12, atol=1e-12)
        worst = max(worst, np.abs(np.array(ys[k + 1].y) - sol.y[:, -1]).max())
    assert worst < 1e-6, worst
    assert procs.interrupt(proc) == 0


def test_the_experiment_runs_on_it(with_user_site, tmp_path):
    """`run_experiment --config config/ci.yaml --family mass_spring_friction --theta ...` as
    scripts/run_experiment.py does it: every phase, the learner's source systems drawn from
    the example's prior, iMAML adapted and tracking, the true-model NMPC from its equations."""
    config = load(os.path.join(ROOT, 'config', 'ci.yaml'),
                  {'family': 'mass_spring_friction', 'theta': THETA,
                   'methods': ['imaml', 'nmpc']})
    assert (config.u_min, config.u_max, config.dt) == ([-2.0], [2.0], 0.1)
    report = run_experiment(config, str(tmp_path / 'run'), progress=False)
    seed = report['per_seed'][0]
    assert seed['complete'] and seed['theta'] == THETA
    for method in ('imaml', 'nmpc'):
        tracking = seed['methods'][method]['tracking']
        assert not tracking['escaped'] and tracking['ticks']['missed'] == 0, method
        assert tracking['input_bounds']['u_max'] == [2.0]
    assert set(seed['methods']['nmpc']['tracking']['planner']) == {'nmpc'}
