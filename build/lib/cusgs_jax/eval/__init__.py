"""Evaluation: image and feature-field metrics, and plots of run results."""
