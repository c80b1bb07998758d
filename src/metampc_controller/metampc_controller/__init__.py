"""Neural state-space model and latent linear MPC: cores and the controller node."""
