"""Console-script entry points: the node module is imported after Ctrl-C is handled.

A node module imports torch, rclpy and numpy (1.5-2 s for the controller and the learner);
Ctrl-C in that time used to end in a KeyboardInterrupt traceback and exit status 130, where
:func:`metampc_common.node_main.run_node` promises exit status 0.
"""
import importlib
import signal
from typing import List, Optional, Sequence


def run(module: str, args: Optional[Sequence[str]] = None) -> int:
    """Import `module` and return its ``main(args)``; 0 at once if Ctrl-C came while importing."""
    seen: List[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    node_module = importlib.import_module(module)
    return 0 if seen else node_module.main(args)
