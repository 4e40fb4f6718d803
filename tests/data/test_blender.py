"""Blender / NeRF-synthetic scenes (data/blender.py): poses, intrinsics, compositing, split, errors."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.frames import opengl_c2w_to_viewmat
from cusgs_jax.data.loader import load_scene
from cusgs_jax.testing.transforms_scenes import gl_look_at, opencv_look_at, write_blender_scene

W, H = 16, 12


@pytest.fixture
def blender(tmp_path):
    return write_blender_scene(tmp_path / "lego", width=W, height=H)


def _project(viewmat, K, point):
    """Pixel (u, v) of a world point: K · (R p + t) / z."""
    cam = viewmat[:3, :3] @ np.asarray(point, np.float64) + viewmat[:3, 3]
    uvw = np.asarray(K, np.float64) @ cam
    return uvw[:2] / uvw[2], cam[2]


def _edit(path, change):
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_pose_conversion_closed_form(tmp_path):
    """A camera at (0, 0, 4) looking at the origin (OpenGL: identity rotation) sees the origin at the
    image centre, +x world to the right of it and +y world ABOVE it (smaller pixel y)."""
    c2w = np.eye(4)
    c2w[2, 3] = 4.0
    view = opengl_c2w_to_viewmat(c2w.tolist(), "frames[0]", tmp_path / "t.json")
    np.testing.assert_allclose(view[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    f = 0.5 * W / math.tan(0.5 * 0.69)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    centre, depth = _project(view, K, [0, 0, 0])
    np.testing.assert_allclose(centre, [W / 2, H / 2], atol=1e-12)
    assert depth == pytest.approx(4.0)
    (u, v), _ = _project(view, K, [1, 0, 0])
    assert u == pytest.approx(W / 2 + f / 4) and v == pytest.approx(H / 2)
    (u, v), _ = _project(view, K, [0, 1, 0])
    assert u == pytest.approx(W / 2) and v == pytest.approx(H / 2 - f / 4)  # above the centre


def test_pose_matches_an_independent_opencv_look_at(tmp_path):
    rng = np.random.default_rng(3)
    for _ in range(5):
        eye, target = rng.normal(size=3) * 4, rng.normal(size=3) * 0.3
        view = opengl_c2w_to_viewmat(gl_look_at(eye, target).tolist(), "frames[0]", tmp_path / "t.json")
        np.testing.assert_allclose(view, opencv_look_at(eye, target), atol=1e-12)
        assert view[2, :3] @ (target - eye) > 0  # the target is in front (z > 0)


def test_loads_cameras_images_and_split(blender):
    scene = load_scene(blender["root"], DataConfig(format="blender"))
    assert scene.names == tuple(blender["names"])
    assert scene.dataset_format == "blender" and scene.split == "transforms_test"
    np.testing.assert_array_equal(scene.train_indices, [0, 1, 2, 3])
    np.testing.assert_array_equal(scene.test_indices, [4, 5])  # the test frames; val ignored
    assert scene.images.shape == (6, H, W, 3) and scene.images.dtype == np.uint8
    assert (scene.width, scene.height) == (W, H)
    f = 0.5 * W / math.tan(0.5 * blender["angle_x"])
    np.testing.assert_allclose(scene.Ks, np.repeat([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]], 6, 0), rtol=1e-6)
    assert scene.Ks.dtype == np.float32 and scene.viewmats.dtype == np.float64
    for view, c2w in zip(scene.viewmats, blender["c2w"]):
        np.testing.assert_allclose(view, opencv_look_at(c2w[:3, 3]), atol=1e-9)
        origin, depth = _project(view, scene.Ks[0], [0, 0, 0])  # every camera looks at the origin
        np.testing.assert_allclose(origin, [W / 2, H / 2], atol=1e-4)
        assert depth == pytest.approx(4.0)
    np.testing.assert_allclose(scene.camera_centers, blender["c2w"][:, :3, 3], atol=1e-9)


def test_rgba_composited_on_white_by_default(blender):
    scene = load_scene(blender["root"], DataConfig(format="blender"))
    assert scene.background == (1.0, 1.0, 1.0)
    rgba = blender["images"].astype(np.float64)
    a = rgba[..., 3:] / 255.0
    expected = np.round(rgba[..., :3] * a + 255.0 * (1 - a)).astype(np.uint8)
    np.testing.assert_array_equal(scene.images, expected)
    assert np.all(scene.images[:, 0, 0] == 255)  # the transparent pixel is white
    black = load_scene(blender["root"], DataConfig(format="blender"), background=(0.0, 0.0, 0.0))
    assert black.background == (0.0, 0.0, 0.0) and np.all(black.images[:, 0, 0] == 0)


def test_random_points_and_extent(blender):
    scene = load_scene(blender["root"], DataConfig(format="blender", random_points=500), seed=1)
    assert scene.points.shape == (scene.carving.kept, 3) and scene.points.dtype == np.float64
    assert scene.carving.points == 500 and scene.carving.kept > 0
    assert scene.point_colors.shape == (scene.carving.kept, 3) and scene.point_colors.dtype == np.uint8
    assert scene.random_points == "cube"  # data.random_init=auto on a Blender scene
    assert np.all(np.abs(scene.points) < 2.0)  # in a cube around the origin the cameras look at
    again = load_scene(blender["root"], DataConfig(format="blender", random_points=500), seed=1)
    np.testing.assert_array_equal(scene.points, again.points)
    centers = blender["c2w"][:, :3, 3]
    assert scene.extent == pytest.approx(1.1 * np.max(np.linalg.norm(centers - centers.mean(0), axis=-1)))


def test_random_points_come_from_the_training_cameras_only(blender):
    """The held-out (test) cameras never shape the initial points: moving them changes nothing; moving a
    training camera does. Both rules."""
    for init in ("cube", "cube_and_rays"):
        data = DataConfig(format="blender", random_points=400, random_init=init)
        before = load_scene(blender["root"], data, seed=2).points
        test_json = blender["root"] / "transforms_test.json"
        original = test_json.read_text()
        _edit(test_json, lambda m: [f["transform_matrix"][i].__setitem__(3, f["transform_matrix"][i][3] + 5.0)
                                    for f in m["frames"] for i in range(3)])
        np.testing.assert_array_equal(
            load_scene(blender["root"], data, seed=2).points, before)
        test_json.write_text(original)
    train_json = blender["root"] / "transforms_train.json"
    _edit(train_json, lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, 9.0))
    moved = load_scene(blender["root"], DataConfig(format="blender", random_points=400, random_init="cube_and_rays"),
                       seed=2).points
    assert not np.array_equal(moved, before)


def test_downscale(tmp_path):
    truth = write_blender_scene(tmp_path / "s", width=32, height=24)
    full = load_scene(truth["root"], DataConfig(format="blender"))
    half = load_scene(truth["root"], DataConfig(format="blender", downscale=2))
    assert half.images.shape == (6, 12, 16, 3)
    np.testing.assert_allclose(half.Ks[:, :2], full.Ks[:, :2] / 2, rtol=1e-6)
    expected = full.images.reshape(6, 12, 2, 16, 2, 3).mean(axis=(2, 4))
    assert np.max(np.abs(half.images - expected)) <= 1.0


def test_without_test_file_there_are_no_held_out_views(blender):
    (blender["root"] / "transforms_test.json").unlink()
    scene = load_scene(blender["root"], DataConfig(format="blender"))
    assert scene.split == "none" and len(scene.test_indices) == 0 and len(scene.train_indices) == 4


def test_file_path_with_extension_and_rgb_images(tmp_path):
    truth = write_blender_scene(tmp_path / "s", rgba=False)
    _edit(truth["root"] / "transforms_train.json",
          lambda m: m["frames"][0].update(file_path="./train/r_0.png"))
    scene = load_scene(truth["root"], DataConfig(format="blender"))
    np.testing.assert_array_equal(scene.images, truth["images"])


# --- errors: each a SceneError naming the file and the fix ----------------------------------


def test_error_malformed_json(blender):
    (blender["root"] / "transforms_train.json").write_text('{"camera_angle_x": 0.6, "frames": [')
    with pytest.raises(SceneError, match=r"transforms_train.json is not valid JSON \(line 1"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_missing_camera_angle_x(blender):
    _edit(blender["root"] / "transforms_test.json", lambda m: m.pop("camera_angle_x"))
    with pytest.raises(SceneError, match=r"transforms_test.json has no \"camera_angle_x\" key.*re-export"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_bad_camera_angle_x(blender):
    _edit(blender["root"] / "transforms_train.json", lambda m: m.update(camera_angle_x=40))
    with pytest.raises(SceneError, match=r"camera_angle_x=40 .* radians"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_missing_frames(blender):
    _edit(blender["root"] / "transforms_train.json", lambda m: m.pop("frames"))
    with pytest.raises(SceneError, match=r"transforms_train.json has no \"frames\" key"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_missing_transform_matrix(blender):
    _edit(blender["root"] / "transforms_train.json", lambda m: m["frames"][2].pop("transform_matrix"))
    with pytest.raises(SceneError, match=r"frames\[2\] in .*transforms_train.json has no \"transform_matrix\""):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_missing_image(blender):
    (blender["root"] / "test" / "r_1.png").unlink()
    with pytest.raises(SceneError, match=r"frames\[1\] of .*transforms_test.json names the image './test/r_1'.*"
                                         r"does not exist.*copy the image there"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_nan_matrix(blender):
    _edit(blender["root"] / "transforms_train.json",
          lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")))
    with pytest.raises(SceneError, match=r"frames\[1\].transform_matrix in .*transforms_train.json contains NaN"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_wrong_matrix_shape(blender):
    _edit(blender["root"] / "transforms_train.json",
          lambda m: m["frames"][0].update(transform_matrix=np.eye(3).tolist()))
    with pytest.raises(SceneError, match=r"frames\[0\].transform_matrix .* shape \(3, 3\); expected a 4x4"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_ragged_matrix(blender):
    _edit(blender["root"] / "transforms_train.json",
          lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0, 0], [0, 1, 0]]))
    with pytest.raises(SceneError, match=r"not a matrix"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_scaled_matrix(blender):
    _edit(blender["root"] / "transforms_train.json",
          lambda m: m["frames"][0].update(transform_matrix=(np.diag([2.0, 2.0, 2.0, 1.0])).tolist()))
    with pytest.raises(SceneError, match=r"not a rigid camera pose"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_images_of_different_sizes(blender):
    iio.imwrite(blender["root"] / "test" / "r_0.png", np.zeros((H, W + 4, 4), np.uint8))
    with pytest.raises(SceneError, match=r"transforms_train.json and .*transforms_test.json do not share one size: "
                                         r"'train/r_0.png' is 16x12 but 'test/r_0.png'"):
        load_scene(blender["root"], DataConfig(format="blender"))


def test_error_no_train_file(tmp_path):
    with pytest.raises(SceneError, match=r"transforms_train.json does not exist.*data.format"):
        load_scene(tmp_path, DataConfig(format="blender"))


def test_a_downscale_that_leaves_no_pixel_is_refused(blender):
    with pytest.raises(SceneError, match=r"data\.downscale=64 shrinks the images \(16x12 in .*transforms_train\.json\) "
                                         r"to 0x0 pixels; use data\.downscale=1"):
        load_scene(blender["root"], DataConfig(format="blender", downscale=64))


def test_error_corrupt_image(blender):
    (blender["root"] / "train" / "r_3.png").write_bytes(b"not a png")
    with pytest.raises(SceneError, match=r"cannot decode image .*r_3.png.*corrupt or not an image.*delete its frame"
                       ) as raised:
        load_scene(blender["root"], DataConfig(format="blender"))
    assert "pip install" not in str(raised.value)
    (blender["root"] / "train" / "r_3.png").write_bytes(b"")
    with pytest.raises(SceneError, match=r"image .*r_3.png is an empty file \(0 bytes\)"):
        load_scene(blender["root"], DataConfig(format="blender"))
