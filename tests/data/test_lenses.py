"""data/lenses.py and data.undistort=lens: distorted scenes kept as captured, rendered through their lens.

The tiny distorted scenes of :mod:`cusgs_jax.testing.distorted_scenes` show a marker around the ray of
every 3D point; loaded with ``data.undistort=lens``, the images are the files themselves and each
marker must sit where the projection through the scene's Camera (lens included) puts its point.
"""

from __future__ import annotations

import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from cusgs_jax.config import DataConfig  # noqa: E402
from cusgs_jax.data.colmap import SceneError  # noqa: E402
from cusgs_jax.data.loader import load_scene  # noqa: E402
from cusgs_jax.data.lenses import (WIDENINGS, check_undistortable, lens_coefficients, lens_of_camera,  # noqa: E402
                                    scene_lens)
from cusgs_jax.splat.project import project_gaussians  # noqa: E402
from cusgs_jax.testing.distorted_scenes import (BACKGROUND, CAMERAS, N_VIEWS, POINTS,  # noqa: E402
                                                distorted_colmap_scene)
from cusgs_jax.types import Camera  # noqa: E402


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _camera(model, params, width=64, height=48):
    return pycolmap.Camera(model=model, width=width, height=height, params=list(params))


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_coefficients_in_colmap_order(model):
    coeffs, fisheye = lens_coefficients(_camera(model, CAMERAS[model]))
    params = CAMERAS[model]
    expected = {"SIMPLE_RADIAL": lambda p: [p[3], 0, 0, 0, 0, 0], "RADIAL": lambda p: [p[3], p[4], 0, 0, 0, 0],
                "OPENCV": lambda p: [p[4], p[5], 0, 0, p[6], p[7]],
                "OPENCV_FISHEYE": lambda p: [p[4], p[5], p[6], p[7], 0, 0],
                "FULL_OPENCV": lambda p: [p[4], p[5], p[8], 0, p[6], p[7]]}[model](params)
    np.testing.assert_array_equal(coeffs, expected)
    assert fisheye == (model == "OPENCV_FISHEYE")


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_trusted_box_covers_the_image_and_is_widened(model):
    camera = _camera(model, CAMERAS[model])
    _, box, _ = lens_of_camera(camera, "camera 1")
    # Every pixel of the image unprojects into the box, with the full widening for these mild lenses.
    jj, ii = np.meshgrid(np.linspace(0, 64, 33), np.linspace(0, 48, 25))
    uv = camera.cam_from_img(np.stack([jj.ravel(), ii.ravel()], -1))
    lo, hi = uv.min(0), uv.max(0)
    np.testing.assert_allclose(box, [lo[0] - (hi[0] - lo[0]) / 2, hi[0] + (hi[0] - lo[0]) / 2,
                                     lo[1] - (hi[1] - lo[1]) / 2, hi[1] + (hi[1] - lo[1]) / 2], rtol=1e-6)


def test_strong_barrel_lens_gets_a_narrower_box_and_a_folding_one_is_refused():
    # r_d = r (1 + k1 r²) with k1 = −0.2 turns back at r = 1/sqrt(3·0.2) ≈ 1.291; the image corner
    # (r_d = 0.8) unprojects to r = 1.0, so a box widened by 100 % or 50 % would reach past the turn.
    camera = _camera("SIMPLE_RADIAL", (50.0, 32.0, 24.0, -0.2))
    _, box, _ = lens_of_camera(camera, "camera 1")
    corner = np.abs(camera.cam_from_img(np.array([[0.0, 0.0]])))[0]
    assert np.all(np.abs(box) >= np.repeat(corner, 2) - 1e-9)  # still covers the image
    assert np.hypot(box[1], box[3]) < 1.291  # and stays where the lens is one-to-one
    assert np.hypot(box[1], box[3]) > np.hypot(*corner)
    # k1 = −2: the frame itself folds (turning radius 0.41 inside the image's 0.8)
    with pytest.raises(SceneError, match=r"camera 7: .*not one-to-one over the image.*data.undistort=crop"):
        lens_of_camera(_camera("SIMPLE_RADIAL", (50.0, 32.0, 24.0, -2.0)), "camera 7")
    assert WIDENINGS[-1] == 0.0


def test_a_full_opencv_lens_with_a_rational_part_is_refused():
    params = list(CAMERAS["FULL_OPENCV"])
    params[9] = 0.01  # k4 of FULL_OPENCV: the rational denominator's r² term
    with pytest.raises(SceneError, match=r"camera 2: its FULL_OPENCV lens .* rational part .* data.undistort=crop"):
        lens_of_camera(_camera("FULL_OPENCV", params), "camera 2")


def test_fisheye_and_perspective_cannot_be_mixed():
    cams = [_camera("OPENCV", CAMERAS["OPENCV"]), _camera("OPENCV_FISHEYE", CAMERAS["OPENCV_FISHEYE"])]
    with pytest.raises(SceneError, match="mix OPENCV_FISHEYE cameras with perspective ones"):
        scene_lens(cams, ["camera 1", "camera 2"])


def _marker_offsets(scene):
    """Distance (px) between each marker's intensity centroid in the loaded images and the centre of a
    tiny Gaussian at its point projected through the view's Camera (lens included)."""
    errors = []
    n = len(POINTS)
    for view in range(scene.num_images):
        camera = Camera.of_scene(scene, view)
        proj = project_gaussians(jnp.asarray(POINTS, jnp.float32), jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)),
                                 jnp.full((n, 3), 1e-3), jnp.ones(n), camera.world_to_camera, camera.K,
                                 scene.width, scene.height, lens=camera.lens)
        for p, (u, v) in enumerate(np.asarray(proj.means2d, np.float64)):
            if not (5 <= u <= scene.width - 5 and 5 <= v <= scene.height - 5):
                continue
            j0, i0 = int(u), int(v)
            ii, jj = np.mgrid[i0 - 4:i0 + 5, j0 - 4:j0 + 5]
            w = np.clip(BACKGROUND - scene.images[view][ii, jj, p % 3].astype(np.float64), 0, None)
            errors.append(float(np.hypot((w * (jj + 0.5)).sum() / w.sum() - u, (w * (ii + 0.5)).sum() / w.sum() - v)))
    return errors


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_lens_mode_keeps_the_images_and_renders_markers_in_place(tmp_path, model):
    distorted_colmap_scene(tmp_path / "s", [(model, CAMERAS[model])])
    scene = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="lens"))
    assert scene.valid is None and scene.lens is not None and scene.lens.fisheye == (model == "OPENCV_FISHEYE")
    assert (scene.width, scene.height) == (64, 48)
    for name, image in zip(scene.names, scene.images):
        np.testing.assert_array_equal(image, iio.imread(tmp_path / "s" / "images" / name)[..., :3])
    cam = _camera(model, CAMERAS[model])
    np.testing.assert_allclose(scene.Ks[0], [[cam.focal_length_x, 0, cam.principal_point_x],
                                             [0, cam.focal_length_y, cam.principal_point_y], [0, 0, 1]], rtol=1e-6)
    errors = _marker_offsets(scene)
    assert len(errors) >= N_VIEWS * 4
    assert max(errors) < 0.1, max(errors)  # a marker's centroid moves < 0.1 px under these lenses
    assert not (tmp_path / "cache" / "undistorted").exists()  # nothing was undistorted


def test_lens_mode_downscale_scales_K_and_keeps_the_lens(tmp_path):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])])
    full = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="lens"))
    half = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="lens", downscale=2))
    assert (half.width, half.height) == (32, 24)
    np.testing.assert_allclose(half.Ks[:, :2], full.Ks[:, :2] / 2, rtol=1e-6)
    np.testing.assert_array_equal(half.lens.coeffs, full.lens.coeffs)
    np.testing.assert_array_equal(half.lens.bounds, full.lens.bounds)


def test_lens_mode_on_pinhole_cameras_is_the_plain_scene(tmp_path):
    distorted_colmap_scene(tmp_path / "s", [("PINHOLE", (50.0, 50.0, 32.0, 24.0))])
    plain = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    lens = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="lens"))
    assert lens.lens is None
    np.testing.assert_array_equal(lens.images, plain.images)
    np.testing.assert_array_equal(lens.Ks, plain.Ks)


def test_a_fisheye_wider_than_the_cap_is_kept_within_it_with_a_warning(caplog):
    # f = 10 px on a 64-px image: the border is ~73° (|u| = 3.2 / 2.4 before the lens) — the corners past 84°
    camera = _camera("OPENCV_FISHEYE", (8.0, 8.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0))
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        _, box, fisheye = lens_of_camera(camera, "camera 3")
    assert fisheye and np.all(np.abs(box) <= 10.0) and np.max(np.abs(box)) == 10.0
    assert "camera 3" in caplog.text and "within it" in caplog.text and "data.undistort=crop" in caplog.text


@pytest.mark.parametrize("mode", ["crop", "mask"])
def test_undistorting_refuses_a_folding_lens_and_a_fisheye_past_90_degrees(mode):
    """crop and mask would fill the image with the folded lens's mirrored ring (and mask would score it as
    valid); a fisheye seeing 90° or more off the axis has no pinhole image. The demo's own lenses pass."""
    with pytest.raises(SceneError, match=r"camera 7: .*not one-to-one over the image.*data.undistort=crop or mask"):
        check_undistortable(_camera("SIMPLE_RADIAL", (50.0, 32.0, 24.0, -2.0)), "camera 7", mode)
    with pytest.raises(SceneError, match=rf"camera 3: its OPENCV_FISHEYE lens .* 90° or more off the axis.*"
                                         rf"data.undistort={mode} cannot undistort it: use data.undistort=lens"):
        check_undistortable(_camera("OPENCV_FISHEYE", (20.0, 20.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0)), "camera 3", mode)
    for model, params in CAMERAS.items():  # the test scenes' lenses (strong barrel and fisheye included) pass
        check_undistortable(_camera(model, params), "camera 1", mode)


@pytest.mark.parametrize("mode", ["crop", "mask"])
def test_a_scene_with_a_folding_lens_is_refused_in_every_mode(tmp_path, mode):
    distorted_colmap_scene(tmp_path / "s", [("SIMPLE_RADIAL", (50.0, 32.0, 24.0, -2.0))])
    for undistort in (mode, "lens"):
        with pytest.raises(SceneError, match=r"camera 1 in .*cameras.bin: its SIMPLE_RADIAL lens .*not one-to-one"):
            load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort=undistort))
