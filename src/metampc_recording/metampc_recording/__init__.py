"""Recording and live view: the MCAP recorder, reader and player, the Foxglove live view."""
