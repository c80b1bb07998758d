"""Progress reports of meta-training and adaptation (fields of TrainingProgress.msg)."""
from dataclasses import dataclass
from typing import Callable


@dataclass
class Progress:
    """One report.

    Attributes:
        iteration: outer step (meta-training) or adaptation step just finished, from 1.
        total: steps requested.
        loss: mean meta-test loss of the step (meta-training) or held-out target loss (adapt).
        elapsed: wall time since the phase started, s.
        skipped: tasks skipped so far because their loss or gradient turned non-finite.
        cg_residual: mean relative CG residual of the step's iMAML meta-gradients (NaN if none).
        validation_loss: meta-training's latest validation loss on held-out tasks (NaN if none).
        rollbacks: rollbacks to the best checkpoint so far (meta-training's divergence guard).
        best_iteration: outer step of the best checkpoint so far.
    """

    iteration: int
    total: int
    loss: float
    elapsed: float
    skipped: int = 0
    cg_residual: float = float('nan')
    validation_loss: float = float('nan')
    rollbacks: int = 0
    best_iteration: int = 0


ProgressFn = Callable[[Progress], None]
