"""data/camera_frame.py: data.undistort for COLMAP and nerfstudio cameras, one rule for both."""

from __future__ import annotations

import pathlib

import pytest

pycolmap = pytest.importorskip("pycolmap")

from cusgs_jax.data.camera_frame import frame_cameras  # noqa: E402
from cusgs_jax.data.errors import SceneError  # noqa: E402

OPENCV = (50.0, 50.0, 32.0, 24.0, -0.05, 0.01, 0.0, 0.0)


def _camera(model, params, width=64, height=48):
    return pycolmap.Camera(model=model, width=width, height=height, params=list(params))


def _frame(cameras, mode, calls):
    views = sorted(cameras) * 2

    def undistort():
        calls.append(1)
        return pathlib.Path("/cache/undistorted")

    return frame_cameras(cameras, views, {cid: f"camera {cid}" for cid in cameras},
                         [f"camera {cid}" for cid in views], mode, undistort, "cameras.bin")


@pytest.mark.parametrize("mode", ["crop", "mask", "lens"])
def test_pinhole_cameras_are_kept_in_every_mode(mode):
    cameras = {1: _camera("PINHOLE", (50.0, 50.0, 32.0, 24.0)), 2: _camera("SIMPLE_RADIAL", (50.0, 32.0, 24.0, 0.0))}
    framed = _frame(cameras, mode, [])
    assert framed.cameras is cameras and framed.undistorted is None and framed.lens is None


def test_lens_mode_keeps_the_cameras_with_their_lenses():
    cameras = {1: _camera("OPENCV", OPENCV)}
    framed = _frame(cameras, "lens", [])
    assert framed.cameras is cameras and framed.undistorted is None
    assert framed.lens.coeffs.shape == (2, 6) and not framed.lens.fisheye


@pytest.mark.parametrize("mode", ["crop", "mask"])
def test_undistorting_gives_pinhole_cameras_and_undistorts_the_images_once_when_asked(mode):
    calls = []
    framed = _frame({1: _camera("OPENCV", OPENCV)}, mode, calls)
    assert framed.lens is None and framed.cameras[1].model.name == "PINHOLE"
    assert not calls  # nothing undistorted until the images are read
    assert framed.undistorted() == framed.undistorted() == pathlib.Path("/cache/undistorted")
    assert calls == [1]


def test_undistorting_refuses_a_folding_lens_and_cameras_of_several_sizes():
    with pytest.raises(SceneError, match=r"camera 1: its SIMPLE_RADIAL lens .*not one-to-one"):
        _frame({1: _camera("SIMPLE_RADIAL", (50.0, 32.0, 24.0, -2.0))}, "crop", [])
    cameras = {1: _camera("OPENCV", OPENCV), 2: _camera("OPENCV", OPENCV, width=80, height=60)}
    with pytest.raises(SceneError, match=r"the cameras of cameras.bin do not share one size \(camera 1 is 64x48, "
                                         r"camera 2 80x60\), and data.undistort=mask .* data.undistort=lens"):
        _frame(cameras, "mask", [])
    assert _frame(cameras, "lens", []).lens is not None  # kept as captured: sizes are the shared pass's to check
