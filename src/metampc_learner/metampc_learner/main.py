"""`ros2 run metampc_learner learner` (see metampc_common.entry)."""
from metampc_common.entry import run


def learner(args=None) -> int:
    """The learner node; its exit code."""
    return run('metampc_learner.learner_node', args)
