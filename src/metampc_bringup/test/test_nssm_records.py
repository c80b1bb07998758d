"""analysis/nssm_records.py: the record's sample pairing against the indices written out, and
the NSSM's free-run simulation against its latent recursion written out by hand (one latent
state, a fixed encoder)."""
import numpy as np
import torch

from metampc_bringup.analysis.nssm_records import record_windows, simulate_nssm, trajectory
from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig


def test_trajectory_pairs_each_input_with_the_next_level():
    u, y = np.arange(10.0), 100 + np.arange(10.0)
    t = trajectory(u, y, 2, 6)
    assert t.steps.tolist() == [2, 3, 4]
    assert t.u[:, 0].tolist() == [2, 3, 4] and t.y[:, 0].tolist() == [103, 104, 105]


def test_free_run_simulation_is_the_latent_recursion_from_the_encoded_state():
    # One latent state, the encoder's output fixed by its last bias (z = 0.7 whatever it
    # reads), identity normalisation: y[H+1+j] = C z_j+1 with z_{j+1} = a z_j + b u[H+j].
    cfg = NssmConfig(n_u=1, n_y=1, n_z=1, history=3, hidden=(4,), loss_horizon=2,
                     stable_latent=False)
    model = Nssm(cfg, dtype=torch.float64)
    params = {k: torch.zeros_like(v) for k, v in model.params().items()}
    params['encoder.1.bias'] = torch.tensor([0.7], dtype=torch.float64)
    a, b, c = 0.9, 0.5, 2.0
    params.update(A=torch.tensor([[a]], dtype=torch.float64),
                  B=torch.tensor([[b]], dtype=torch.float64),
                  C=torch.tensor([[c]], dtype=torch.float64))
    rng = np.random.default_rng(0)
    u, y = rng.uniform(0, 5, 12), rng.uniform(0, 5, 12)
    sim = simulate_nssm(model, params, u, y)
    assert np.all(np.isnan(sim[:4]))
    z, expected = 0.7, []
    for k in range(3, 11):
        z = a * z + b * u[k]
        expected.append(c * z)
    np.testing.assert_allclose(sim[4:], expected, rtol=1e-12)


def test_record_windows_are_the_pairs_of_the_record_normalised():
    cfg = NssmConfig(n_u=1, n_y=1, n_z=1, history=3, hidden=(4,), loss_horizon=2,
                     stable_latent=False)
    model = Nssm(cfg, dtype=torch.float64)
    u, y = np.arange(20.0), 100 + np.arange(20.0)
    w = record_windows(model, u, y, 4, 14)      # 9 pairs, 5 = H + T a window: 5 windows
    assert w.u.shape[:2] == (5, 5)
    u_n, y_n = model.norm.normalise(u[4:9, None], y[5:10, None])
    np.testing.assert_allclose(w.u[0].numpy(), u_n)
    np.testing.assert_allclose(w.y[0].numpy(), y_n)
