"""Meta-learning (iMAML, MAML, supervised) of the NSSM: cores and the learner node."""
