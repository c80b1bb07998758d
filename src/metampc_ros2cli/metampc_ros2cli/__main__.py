"""`python -m metampc_ros2cli`: the `ros2` command (:func:`metampc_ros2cli.cli.main`)."""
import sys

from metampc_ros2cli.cli import main

sys.exit(main())
