"""The everyday `ros2` verbs for ROS 2 Jazzy from PyPI wheels, where ros2cli does not exist.

Syntax, options, output formats and exit statuses follow ros2cli (Jazzy); the `ros2` command of
scripts/ros2_shim.py hands every verb but `run` and `pkg` to :func:`metampc_ros2cli.cli.main`.
"""
