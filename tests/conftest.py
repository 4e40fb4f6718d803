"""Shared test fixtures. Random scenes live in :mod:`cusgs_jax.testing.scenes`."""

from __future__ import annotations

import pytest

TINY_DEMO = dict(width=40, height=30, num_views=4, num_points=1500)
"""The tiny demo scene of the ``demo`` fixture (W, H, V as the extract tests use them)."""


@pytest.fixture
def x64():
    """Run a test with float64 enabled in JAX."""
    import jax

    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A tiny demo scene, one per test module (tests write features with overwrite=True)."""
    from cusgs_jax.data.demo import generate_demo_scene

    return generate_demo_scene(tmp_path_factory.mktemp("demo"), **TINY_DEMO)


@pytest.fixture(scope="module")
def names(demo):
    """Image names of the ``demo`` fixture's scene."""
    from cusgs_jax.data.colmap import load_scene

    return load_scene(demo, holdout_every=0).names
