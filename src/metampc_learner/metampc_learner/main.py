"""`ros2 run metampc_learner learner` (see metampc_common.entry), and `adapt_offline`'s old
place (one release: it names the new one)."""
import sys

from metampc_common.entry import run


def learner(args=None) -> int:
    """The learner node; its exit code."""
    return run('metampc_learner.learner_node', args)


def adapt_offline(args=None) -> int:
    """adapt_offline moved to metampc_bringup (it reads --config with the experiment
    configuration's reader): one line saying so, exit status 2."""
    print('adapt_offline: moved: ros2 run metampc_bringup adapt_offline (the same arguments); '
          'this name will be removed in the next release', file=sys.stderr)
    return 2
