"""Checkpoints: exact round trip of config, normalisation and weights; weights_only load."""
import pytest
import torch

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint


def test_round_trip(tmp_path):
    config = NssmConfig(hidden=(32, 8), n_z=4, history=6, loss_horizon=7)
    norm = Normalisation([0.1], [0.5], [0.0, 1.0], [3.0, 2.5])
    params = init_params(config, 12)
    path = str(tmp_path / 'meta.pt')
    save_checkpoint(path, Nssm(config, norm), params, {'method': 'imaml', 'losses': [0.5, 0.2]})
    torch.load(path, weights_only=True)      # plain types only
    ckpt = load_checkpoint(path)
    assert ckpt.model.config == config
    assert ckpt.model.norm.to_dict() == norm.to_dict()
    assert all(torch.equal(ckpt.params[k], params[k]) for k in params)
    assert ckpt.info == {'method': 'imaml', 'losses': [0.5, 0.2]}
    u, y = torch.randn(3, config.window, 1), torch.randn(3, config.window, 2)
    a = torch.func.functional_call(ckpt.model, ckpt.params, (u, y))
    b = torch.func.functional_call(Nssm(config, norm), params, (u, y))
    assert torch.equal(a, b)


def test_reads_a_file_that_calls_the_loss_horizon_horizon(tmp_path):
    config = NssmConfig(hidden=(8,), n_z=2, history=3, loss_horizon=6)
    path = str(tmp_path / 'old.pt')
    save_checkpoint(path, Nssm(config, Normalisation([0.0], [1.0], [0.0, 0.0], [1.0, 1.0])),
                    init_params(config, 1))
    blob = torch.load(path, weights_only=True)
    blob['config']['horizon'] = blob['config'].pop('loss_horizon')
    torch.save(blob, path)
    assert load_checkpoint(path).model.config == config


def test_rejects_foreign_files(tmp_path):
    path = str(tmp_path / 'other.pt')
    torch.save({'weights': torch.zeros(3)}, path)
    with pytest.raises(ValueError, match='not a'):
        load_checkpoint(path)
