"""NssmWeights messages to control with, for runs without a learner (soak, benchmarks): the
hand-built model of :mod:`metampc_model.manual_model` or a learner checkpoint.

No rclpy here (message classes only).
"""
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.nssm import Nssm, torch_params
from metampc_model.weights_codec import fields_from_weights, fields_of, weights_from_fields
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_msgs.msg import NssmWeights


def manual_weights(theta: float, dt: float, version: int = 1, **sizes) -> NssmWeights:
    """The hand-built NSSM (the plant linearised at damping theta, zero-order hold over dt s),
    method 'manual', stage 'adapted'; sizes: history, n_z, hidden (as linearised_vdp_nssm)."""
    return NssmWeights(version=version, method='manual', stage='adapted',
                       **fields_from_weights(*linearised_vdp_nssm(theta, dt, **sizes)))


def checkpoint_weights(path: str, version: int = 1) -> NssmWeights:
    """The model of a checkpoint file, with the method and stage of its info (default: an
    adapted iMAML model)."""
    ckpt = load_checkpoint(path)
    return NssmWeights(version=version, method=ckpt.info.get('method', 'imaml'),
                       stage=ckpt.info.get('stage', 'adapted'),
                       **fields_from_weights(ckpt.model.config, ckpt.model.norm, ckpt.params))


def save_weights(msg: NssmWeights, path: str) -> None:
    """Write the model of a weights message (e.g. read from a recording) as a checkpoint,
    with its method and stage: a learner loads it with ``meta_model_path``."""
    decoded = weights_from_fields(fields_of(msg))
    save_checkpoint(path, Nssm(decoded.config, decoded.norm), torch_params(decoded.params),
                    {'method': msg.method, 'stage': msg.stage, 'version': int(msg.version),
                     'train_loss': float(msg.train_loss), 'train_steps': int(msg.train_steps),
                     'train_samples': int(msg.train_samples), 'seed': int(msg.seed)})
