"""Latent linear MPC on the shared NSSM: cores and the controller node."""
