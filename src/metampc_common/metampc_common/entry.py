"""Console-script entry points: the node module is imported after Ctrl-C is handled.

A node module imports torch, rclpy and numpy, which takes seconds; Ctrl-C in that time ends the
command with exit status 0, as :func:`metampc_common.node_main.run_node` promises, not with a
KeyboardInterrupt traceback (docs/nodes.md).
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
