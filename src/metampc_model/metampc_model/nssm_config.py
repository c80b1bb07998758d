"""The NSSM's architecture (eq. SSM): its sizes, training-loss settings and parameter shapes.

No torch: the controller reads a model's architecture from its weights message without the
training side (``nssm.py``, where the model itself and its losses are).
"""
from collections import OrderedDict
from dataclasses import dataclass
from typing import Tuple

from metampc_common.params import check_fields, param


@dataclass
class NssmConfig:
    """Architecture of the NSSM.

    Attributes:
        n_u: inputs.
        n_y: outputs.
        n_z: latent dimension (paper: 5).
        history: H, samples of (u, y) the encoder reads.
        hidden: widths of the encoder's ReLU hidden layers (paper: 128, 128).
        loss_horizon: T, prediction steps of the training loss (the MPC's horizon is N).
        stable_latent: A of eq. (z_next) bounded to spectral norm < rho_max by the smooth map
            of ``latent_stability.py`` (False: A free, as in the paper).
        rho_max: the bound (> 0).
        consistency_weight: w of the latent consistency term in the training loss (>= 0; 0:
            l_SSM alone, the paper's loss; ``nssm.py``'s docstring).
    """

    n_u: int = 1
    n_y: int = 2
    n_z: int = param(5, 'latent dimension', ge=1)
    history: int = param(10, 'H, samples the encoder reads', ge=1)
    hidden: Tuple[int, ...] = param((128, 128), 'widths of the encoder ReLU layers', ge=1)
    loss_horizon: int = param(10, 'T, prediction steps of the loss', ge=1, formerly='horizon')
    stable_latent: bool = param(True, 'bound the spectral norm of A by rho_max (false: A free, '
                                      'as in the paper)')
    rho_max: float = param(1.0, 'bound of the spectral norm of A', gt=0)
    consistency_weight: float = param(0.0, 'w of the latent consistency term of the training '
                                           'loss (0: l_SSM alone, as in the paper)', ge=0)

    def __post_init__(self):
        self.hidden = tuple(int(w) for w in self.hidden)
        self.stable_latent = bool(self.stable_latent)
        self.rho_max = float(self.rho_max)
        self.consistency_weight = float(self.consistency_weight)

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)
        for name in ('n_u', 'n_y'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')

    @property
    def window(self) -> int:
        """Samples in one training window, H + T."""
        return self.history + self.loss_horizon


def param_shapes(config: NssmConfig) -> 'OrderedDict[str, Tuple[int, ...]]':
    """Names and shapes of the parameters, in canonical order."""
    widths = [config.history * (config.n_u + config.n_y), *config.hidden, config.n_z]
    shapes = OrderedDict()
    for i, (fan_in, fan_out) in enumerate(zip(widths[:-1], widths[1:])):
        shapes[f'encoder.{i}.weight'] = (fan_out, fan_in)
        shapes[f'encoder.{i}.bias'] = (fan_out,)
    shapes['A'] = (config.n_z, config.n_z)
    shapes['B'] = (config.n_z, config.n_u)
    shapes['C'] = (config.n_y, config.n_z)
    return shapes
