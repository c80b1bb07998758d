"""`ros2 run metampc_plant plant` and `bridge` (see metampc_common.entry)."""
from metampc_common.entry import run


def plant(args=None) -> int:
    """The plant node; its exit code."""
    return run('metampc_plant.plant_node', args)


def bridge(args=None) -> int:
    """The machine bridge node; its exit code."""
    return run('metampc_plant.bridge_node', args)
