"""`ros2 run metampc_recording recorder|foxglove` (see metampc_common.entry)."""
from metampc_common.entry import run


def recorder(args=None) -> int:
    """The recorder node; its exit code."""
    return run('metampc_recording.recorder_node', args)


def foxglove(args=None) -> int:
    """The Foxglove live-view node; its exit code."""
    return run('metampc_recording.foxglove_node', args)
