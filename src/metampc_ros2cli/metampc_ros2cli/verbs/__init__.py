"""One module per `ros2` verb family; each has ``add_parser(subparsers)``."""
