"""Learning studies without ROS: the job runner (offline), the hyperparameter search (tuning),
the inner-steps sweep and the robustness runs."""
