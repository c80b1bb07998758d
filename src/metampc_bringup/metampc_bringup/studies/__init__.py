"""Learning studies without ROS: the job runner (learning_setup), the hyperparameter search
(tuning), the inner-steps sweep and the robustness runs."""
