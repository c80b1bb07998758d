"""The flat training vector: exact round trips, W in the vector and A in the published weights."""
import torch

from metampc_model.nssm import init_params
from metampc_model.nssm_config import NssmConfig
from metampc_learner.training_vector import TrainingVector

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_round_trip_is_exact():
    """Exact for a free A; the stable A goes through W and back (test_latent_stability.py)."""
    config = NssmConfig(stable_latent=False)
    spec = TrainingVector(config)
    params = init_params(config, 2)
    flat = spec.flatten(params)
    assert flat.shape == (spec.size,)
    back = spec.unflatten(flat)
    assert all(torch.equal(back[k], params[k]) for k in params)
    stable = TrainingVector(NssmConfig())
    back = stable.unflatten(stable.flatten(init_params(NssmConfig(), 2)))
    assert all(torch.equal(back[k], params[k]) for k in params if k != 'A')


def test_flat_vector_holds_w_and_published_weights_hold_a():
    config = NssmConfig(hidden=(8,), n_z=4, history=3, rho_max=0.7)
    params = init_params(config, seed=5, dtype=F64)
    assert float(torch.linalg.matrix_norm(params['A'], ord=2)) < 0.7
    spec = TrainingVector(config)
    flat = spec.flatten(params)
    back = spec.unflatten(flat)
    for name in params:
        torch.testing.assert_close(back[name], params[name], rtol=1e-10, atol=1e-12)
    # any training vector at all maps to a stable A, batched too
    wild = 100.0 * torch.randn(3, spec.size, generator=_gen(6), dtype=F64)
    a = spec.unflatten(wild)['A']
    assert a.shape == (3, 4, 4)
    # <=: at this scale tanh rounds to 1 and the norm is rho_max to rounding
    assert torch.all(torch.linalg.matrix_norm(a, ord=2) <= 0.7 * (1 + 1e-12))
    free = NssmConfig(hidden=(8,), n_z=4, history=3, stable_latent=False)
    raw = init_params(free, seed=5, dtype=F64)
    vector = TrainingVector(free)
    assert torch.equal(vector.unflatten(100.0 * vector.flatten(raw))['A'], 100.0 * raw['A'])
