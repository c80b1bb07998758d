"""`ros2 run metampc_controller controller | send_model` (see metampc_common.entry)."""
from metampc_common.entry import run


def controller(args=None) -> int:
    """The controller node; its exit code."""
    return run('metampc_controller.controller_node', args)


def send_model(args=None) -> int:
    """The node that publishes the hand-built model; its exit code."""
    return run('metampc_controller.send_model_node', args)
