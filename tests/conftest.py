"""Shared test fixtures. Random scenes live in :mod:`cusgs_jax.testing.scenes`."""

from __future__ import annotations

import pytest


@pytest.fixture
def x64():
    """Run a test with float64 enabled in JAX."""
    import jax

    with jax.enable_x64(True):
        yield
