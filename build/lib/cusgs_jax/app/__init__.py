"""Command-line entry points and the training run (the imperative shell)."""
