"""What every per-task meta-gradient returns (iMAML, first-order and unrolled MAML)."""
from typing import NamedTuple

import torch


class TaskGradient(NamedTuple):
    """Per task b (a leading batch dimension B under vmap).

    Attributes:
        grad: the task's contribution to the outer update (P,).
        test_loss: l_SSM(D_test; omega_b), scalar.
        cg_residual: relative CG residual, scalar (NaN where no CG runs).
        adapted: omega_b, the inner loop's result (P,).
    """

    grad: torch.Tensor
    test_loss: torch.Tensor
    cg_residual: torch.Tensor
    adapted: torch.Tensor
