"""cusgs-jax's Hydra plugins (Hydra only instantiates plugin classes defined under ``hydra_plugins``)."""
