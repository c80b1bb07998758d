"""The real-time soak: the controller at its rate for a long time, observed and measured."""
