"""`ros2 run metampc_controller controller` (see metampc_common.entry)."""
from metampc_common.entry import run


def controller(args=None) -> int:
    """The controller node; its exit code."""
    return run('metampc_controller.controller_node', args)
