"""viser camera ↔ our Camera: round trips, intrinsics of the browser's view, scene up, orbit centre."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.view.camera import (from_viser, intrinsics, look_at_point, render_size, scene_up, to_viser,
                                   world_to_camera)


def _random_viewmat(seed):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = q, rng.normal(size=3)
    return m


@pytest.mark.parametrize("seed", range(4))
def test_a_training_camera_survives_the_trip_through_viser(seed):
    viewmat = _random_viewmat(seed)
    K = intrinsics(0.9, 40, 30)
    wxyz, position, fov = to_viser(K, viewmat, 30)
    assert fov == pytest.approx(0.9)
    np.testing.assert_allclose(world_to_camera(wxyz, position), viewmat, atol=1e-5)
    cam = from_viser(wxyz, position, fov, 40, 30)
    np.testing.assert_allclose(np.asarray(cam.K), K, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(cam.center), position, atol=1e-5)


def test_intrinsics_put_the_vertical_fov_on_the_image_height():
    K = intrinsics(np.pi / 2, 64, 32)  # 90°: f = H/2
    np.testing.assert_allclose(K, [[16, 0, 32], [0, 16, 16], [0, 0, 1]])
    assert render_size(4 / 3, 480) == (640, 480) and render_size(0.001, 10) == (1, 10)


def test_scene_up_and_look_at_point():
    level = np.eye(4)  # OpenCV camera at the origin: up is −y
    assert np.allclose(scene_up([level, level]), [0, -1, 0])
    point = look_at_point(level, [0.3, 0.0, 2.0])
    np.testing.assert_allclose(point, [0, 0, 2.0])  # straight ahead at the target's depth
    behind = look_at_point(level, [0.0, 0.0, -2.0])
    assert behind[2] > 0  # never behind the camera
