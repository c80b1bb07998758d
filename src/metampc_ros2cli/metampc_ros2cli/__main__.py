import sys

from metampc_ros2cli.cli import main

sys.exit(main())
