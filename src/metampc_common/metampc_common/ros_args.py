"""The command-line form of ROS parameters, remaps and a node name (`--ros-args ...`).

What `ros2 run PKG EXE` and a console entry point are given to start a node as configured; its
parameter values are written as YAML, as rcl parses them. No rclpy here.
"""
from typing import Dict, List, Optional


def ros_args(params: Optional[Dict[str, object]] = None, remaps: Optional[Dict[str, str]] = None,
             name: Optional[str] = None) -> List[str]:
    """`--ros-args -p k:=v -r a:=b` arguments; lists become YAML lists, bools true/false."""
    args = ['--ros-args']
    for key, value in (params or {}).items():
        args += ['-p', f'{key}:={_yaml(value)}']
    for src, dst in (remaps or {}).items():
        args += ['-r', f'{src}:={dst}']
    if name:
        args += ['-r', f'__node:={name}']
    return args


def _yaml(value: object) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_yaml(v) for v in value) + ']'
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'" if value else "''"
    return repr(value) if isinstance(value, float) else str(value)
