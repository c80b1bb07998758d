"""`ros2 run metampc_learner learner` and `adapt_offline` (see metampc_common.entry)."""
from metampc_common.entry import run


def learner(args=None) -> int:
    """The learner node; its exit code."""
    return run('metampc_learner.learner_node', args)


def adapt_offline(args=None) -> int:
    """Adaptation from a recording (metampc_learner.adapt_offline); its exit status."""
    return run('metampc_learner.adapt_offline', args)
