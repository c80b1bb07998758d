"""The experiment of the paper on the ROS 2 graph, and its analysis, studies and soak.

On top: ``experiment_config`` (the experiment, checked), ``experiment_events`` (what the
orchestrator records, typed) and ``experiment`` (run it, report it). By role, each importing
the top and lower roles only: ``orchestration``, ``analysis`` (no rclpy), ``studies``, ``soak``.
"""
