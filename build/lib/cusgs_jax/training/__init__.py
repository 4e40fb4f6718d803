"""Training: the state, the jitted step, the optimiser, rendering helpers and checkpoints."""
