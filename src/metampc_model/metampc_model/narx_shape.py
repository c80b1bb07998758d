"""The feature NARX's sizes and parameter shapes (:mod:`metampc_model.feature_narx`).

No torch: the controller reads a feature NARX's sizes from its weights message without the
training side, as it reads an NSSM's (:mod:`metampc_model.nssm_config`). The sizes a user
chooses are node parameters of the learner (``narx_order``, ``narx_features``,
``narx_hidden``), declared here once.
"""
from collections import OrderedDict
from dataclasses import dataclass
from typing import Dict, Tuple

from metampc_common.params import param


@dataclass(frozen=True)
class NarxShape:
    """Sizes of a feature NARX.

    Attributes:
        n_u, n_y: inputs, outputs.
        order: p, lags of the regressor state (>= 1).
        features: F, meta-learned features (0: the ARX).
        hidden: widths of g's hidden tanh layers.
    """

    n_u: int
    n_y: int
    order: int = param(2, 'p, lags of the regressor state s_t (outputs y_t..y_{t-p+1}, inputs '
                          'u_t..u_{t-p+2})', ge=1)
    features: int = param(32, 'F, meta-learned tanh features g(s_t) (0: the ARX(p))', ge=0)
    hidden: Tuple[int, ...] = param((64,), "widths of g's hidden tanh layers", ge=1)

    def __post_init__(self):
        if min(self.n_u, self.n_y, self.order) < 1 or self.features < 0 or any(
                w < 1 for w in self.hidden):
            raise ValueError(f'feature NARX needs n_u, n_y, order >= 1, features >= 0 and '
                             f'hidden widths >= 1, got {self}')

    @property
    def n_s(self) -> int:
        """Size of the regressor state s_t."""
        return self.order * self.n_y + (self.order - 1) * self.n_u

    @property
    def n_phi(self) -> int:
        """Size of the regressor phi."""
        return self.n_s + self.features + self.n_u + 1

    def feature_shapes(self) -> Dict[str, Tuple[int, ...]]:
        """g's parameters, canonical order: g.<i>.weight (out, in), g.<i>.bias (out,)."""
        widths = [self.n_s, *self.hidden, self.features]
        shapes = {}
        for i in range(len(widths) - 1):
            shapes[f'g.{i}.weight'] = (widths[i + 1], widths[i])
            shapes[f'g.{i}.bias'] = (widths[i + 1],)
        return shapes if self.features else {}

    def param_shapes(self) -> 'OrderedDict[str, Tuple[int, ...]]':
        """Every parameter, canonical order: g's (:meth:`feature_shapes`), then 'head'
        (n_y, n_phi)."""
        return OrderedDict([*self.feature_shapes().items(), ('head', (self.n_y, self.n_phi))])


__all__ = ['NarxShape']
