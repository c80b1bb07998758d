"""analysis/twin.py: the tracking run on the cascaded tanks' twin (config/cascaded_tanks.yaml,
a short run): the plant is the family at the given theta and x0 (checked against scipy's
integration of the equations), its first set-point is the steady level in closed form, the
true-model NMPC holds it, and a latent MPC on an untrained NSSM flies the same reference but
tracks worse."""
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
import torch

from metampc_bringup.analysis.twin import nssm_weights, track_twin
from metampc_bringup.experiment_config import learner_config, load
from metampc_model.nssm import Nssm
from metampc_model.normalisation import Normalisation
from metampc_plant.registry import get_family

ROOT = Path(__file__).resolve().parents[3]
# The grey-box fit to all 1024 estimation samples (docs/real_data.md) and its x(0).
THETA = (0.05273, 0.03257, 0.03598, 0.04748, 0.01335)
X0 = (6.959, 5.058)


def _experiment():
    experiment = load(str(ROOT / 'config' / 'cascaded_tanks.yaml'))
    # 30 samples (120 s) of the first set-point; a shorter horizon keeps the NMPC quick.
    return replace(experiment, track_duration=120.0,
                   controller={**experiment.controller, 'horizon': 10, 'nmpc_tail': 10})


def test_nmpc_holds_the_twins_steady_level_and_an_untrained_model_does_worse():
    experiment = _experiment()
    k1, k2, k3, k4, _ = THETA
    v = experiment.reference_inputs[0][0]
    setpoint = (k2 / k3) ** 2 * (k4 * v / k1) ** 2       # x1 = (k4 v / k1)^2, no overflow
    cfg = learner_config(experiment, 0).nssm
    torch.manual_seed(0)
    untrained = Nssm(cfg, Normalisation(np.array([3.0]), np.array([1.5]), np.array([5.5]),
                                        np.array([2.0])))
    episodes = {}
    results = track_twin(experiment, THETA, X0, {
        'nmpc': None, 'untrained': nssm_weights(untrained, untrained.params())}, episodes)
    nmpc = episodes['nmpc']
    np.testing.assert_allclose(nmpc.y_ref[:, 0], setpoint, atol=1e-3)
    assert nmpc.escaped_at is None and len(nmpc.y) == 31
    assert abs(nmpc.y[-10:, 0] - setpoint).max() < 0.02      # from 5.06 V to 5.21 V
    # The plant: the family at THETA from X0, each answer held over a sample (scipy).
    family, x = get_family('cascaded_tanks'), np.array(X0)
    for k in range(len(nmpc.u) - 1):
        x = solve_ivp(lambda t, s, u=nmpc.u[k + 1]: family.rhs(s, u, THETA), (0.0, 4.0), x,
                      method='DOP853', rtol=1e-10, atol=1e-10).y[:, -1]
        assert abs(x[1] - nmpc.y[k + 1, 0]) < 2e-3
    assert not results['untrained'].rejected and not results['untrained'].escaped
    assert results['untrained'].cost > results['nmpc'].cost
    assert np.array_equal(episodes['untrained'].y_ref, nmpc.y_ref)
