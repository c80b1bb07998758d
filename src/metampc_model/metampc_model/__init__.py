"""The neural state-space model of eq. (SSM) that learner and controller share: torch and numpy."""
