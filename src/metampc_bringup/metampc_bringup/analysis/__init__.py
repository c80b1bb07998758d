"""What a recording says, without rclpy: series, metrics, plots, the reports of a run, of an
experiment and of a drift experiment, re-tracking, paired statistics."""
