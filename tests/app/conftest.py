"""The demo scene the shell's end-to-end tests share (test_run, test_session, test_loop)."""

from __future__ import annotations

import pytest

from cusgs_jax.data.demo import generate_demo_scene


@pytest.fixture(scope="module")
def tiny_scene(build_once):
    """The 9-view 40×30 demo scene, generated once per session (tests/conftest.py built_once; the runs of
    test_run record its path, so every xdist worker resumes them on the same folder). The feature tests extract
    into its features/ folder, which the library serialises across processes (extract.scene.ensure_extracted)."""
    _, scene = build_once("run_scene", lambda root: generate_demo_scene(
        root / "demo", num_views=9, width=40, height=30, num_points=1500))
    return scene
