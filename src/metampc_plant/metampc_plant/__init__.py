"""Van der Pol plant with uncertain damping: simulator core and the plant node."""
