"""nerfstudio scenes (data/nerfstudio.py): intrinsics, poses, split, points, camera models, errors."""

from __future__ import annotations

import json
import os

import imageio.v3 as iio
import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.loader import load_scene
from cusgs_jax.testing.distorted_scenes import CAMERAS, H, N_VIEWS, W, distorted_colmap_scene, marker_errors, nerfstudio_copy
from cusgs_jax.testing.transforms_scenes import opencv_look_at, write_nerfstudio_scene, write_ply_points

W, H = 16, 12


@pytest.fixture
def ns(tmp_path):
    return write_nerfstudio_scene(tmp_path / "scene", width=W, height=H)


def _edit(root, change):
    path = root / "transforms.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_loads_sorted_frames_with_intrinsics_and_poses(ns):
    scene = load_scene(ns["root"], DataConfig(format="nerfstudio", holdout_every=0))
    assert scene.names == tuple(ns["names"])  # sorted by file_path, whatever the JSON order
    assert scene.dataset_format == "nerfstudio" and scene.split == "none"
    np.testing.assert_array_equal(scene.images, ns["images"])
    K = np.array([[14.0, 0, 8.0], [0, 15.0, 6.5], [0, 0, 1]])
    np.testing.assert_allclose(scene.Ks, np.repeat(K[None], len(ns["names"]), 0))
    for view, c2w in zip(scene.viewmats, ns["c2w"]):
        np.testing.assert_allclose(view, opencv_look_at(c2w[:3, 3]), atol=1e-9)  # applied_transform ignored
    assert scene.background == (0.0, 0.0, 0.0)


def test_holdout_every_nth_sorted_by_file_path(ns):
    scene = load_scene(ns["root"], DataConfig(format="nerfstudio", holdout_every=2))
    np.testing.assert_array_equal(scene.test_indices, [0, 2, 4])
    np.testing.assert_array_equal(scene.train_indices, [1, 3, 5])
    assert scene.split == "every_2nd"
    assert load_scene(ns["root"], DataConfig(format="nerfstudio")).split == "every_8th"
    with pytest.raises(SceneError, match="holds out all"):
        load_scene(ns["root"], DataConfig(format="nerfstudio", holdout_every=1))


def test_per_frame_intrinsics(tmp_path):
    truth = write_nerfstudio_scene(tmp_path / "s", per_frame_intrinsics=True, camera_model=None)
    _edit(truth["root"], lambda m: [f.update(fl_x=20.0) for f in m["frames"] if f["file_path"].endswith("3.png")])
    scene = load_scene(truth["root"], DataConfig(format="nerfstudio"))
    fx = scene.Ks[:, 0, 0]
    assert fx[2] == 20.0 and np.all(np.delete(fx, 2) == 14.0)


def test_ply_points_and_colours(tmp_path):
    truth = write_nerfstudio_scene(tmp_path / "s", ply=True)
    scene = load_scene(truth["root"], DataConfig(format="nerfstudio"))
    np.testing.assert_allclose(scene.points, truth["points"], atol=1e-6)
    np.testing.assert_array_equal(scene.point_colors, truth["colors"])


def test_ply_without_colours_is_grey(tmp_path):
    truth = write_nerfstudio_scene(tmp_path / "s", ply=True)
    write_ply_points(truth["root"] / "sparse_pc.ply", truth["points"])
    scene = load_scene(truth["root"], DataConfig(format="nerfstudio"))
    assert np.all(scene.point_colors == 128) and len(scene.points) == 50


def test_non_finite_ply_points_are_left_out_with_a_warning(tmp_path, caplog):
    truth = write_nerfstudio_scene(tmp_path / "s", ply=True)
    points = truth["points"].copy()
    points[[3, 7], 1] = np.nan
    write_ply_points(truth["root"] / "sparse_pc.ply", points)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        scene = load_scene(truth["root"], DataConfig(format="nerfstudio"))
    assert len(scene.points) == len(points) - 2
    assert "2 of its 50 points have a non-finite coordinate (NaN or Inf) and were left out" in caplog.text


def test_without_ply_random_points(ns):
    """No ply_file_path: data.random_init=auto is cube_and_rays here (a real capture), drawn for the training
    cameras only; cube on request."""
    from cusgs_jax.data.random_points import random_points

    scene = load_scene(ns["root"], DataConfig(format="nerfstudio", random_points=300))
    assert scene.points.shape == (scene.carving.kept, 3) and scene.carving.points == 300
    assert np.all(scene.point_colors == 128)
    assert scene.random_points == "cube_and_rays"
    train = scene.train_indices
    expected, _ = random_points(scene.viewmats[train], scene.Ks[train], scene.width, scene.height, num=300,
                                init="cube_and_rays")
    kept = (expected[:, None] == scene.points[None]).all(-1).any(1)  # carving keeps a subset, in the draw's order
    np.testing.assert_array_equal(expected[kept], scene.points)
    cube = load_scene(ns["root"], DataConfig(format="nerfstudio", random_points=300, random_init="cube"))
    assert cube.random_points == "cube"
    drawn = random_points(scene.viewmats[train], scene.Ks[train], scene.width, scene.height, num=300, init="cube")[0]
    np.testing.assert_array_equal(drawn[(drawn[:, None] == cube.points[None]).all(-1).any(1)], cube.points)


def test_downscale_prefers_images_d(tmp_path):
    w, h = 2 * W, 2 * H  # half of it is still as large as the SSIM window (load_scene refuses less)
    truth = write_nerfstudio_scene(tmp_path / "s", width=w, height=h, prescaled=2)
    (truth["root"] / "images_2" / "frame_00001.png").unlink()  # this one is reduced on the fly
    scene = load_scene(truth["root"], DataConfig(format="nerfstudio", downscale=2, holdout_every=0))
    assert scene.images.shape == (6, h // 2, w // 2, 3)
    np.testing.assert_allclose(scene.Ks[0], [[7.0, 0, 4.0], [0, 7.5, 3.25], [0, 0, 1]])
    expected = truth["images"].reshape(6, h // 2, 2, w // 2, 2, 3).mean(axis=(2, 4))
    assert np.max(np.abs(scene.images - expected)) <= 1.0
    iio.imwrite(truth["root"] / "images_2" / "frame_00002.png", np.zeros((h, w, 3), np.uint8))  # not 2x smaller
    with pytest.raises(SceneError, match=r"frame_00002.png .* is 32x24 but .*transforms.json says it should be 16x12"):
        load_scene(truth["root"], DataConfig(format="nerfstudio", downscale=2))


def test_zero_distortion_opencv_loads(tmp_path):
    truth = write_nerfstudio_scene(tmp_path / "s", distortion=dict(k1=0.0, k2=0.0, k3=0.0, k4=0.0, p1=0.0, p2=0.0))
    assert load_scene(truth["root"], DataConfig(format="nerfstudio", undistort="crop")).num_images == 6


# --- errors: each a SceneError naming the file and the fix ----------------------------------


def test_error_malformed_json(ns):
    (ns["root"] / "transforms.json").write_text("{'frames': []}")
    with pytest.raises(SceneError, match=r"transforms.json is not valid JSON.*ns-process-data"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_missing_intrinsics(ns):
    _edit(ns["root"], lambda m: (m.pop("fl_x"), m.pop("h")))
    with pytest.raises(SceneError, match=r"frames\[0\] of .*transforms.json has no fl_x, h \(neither in the frame "
                                         r"nor at the top level\)"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_missing_frames(ns):
    _edit(ns["root"], lambda m: m.pop("frames"))
    with pytest.raises(SceneError, match=r"transforms.json has no \"frames\" key"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_missing_transform_matrix(ns):
    _edit(ns["root"], lambda m: m["frames"][4].pop("transform_matrix"))
    with pytest.raises(SceneError, match=r"frames\[4\] in .*transforms.json has no \"transform_matrix\""):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_missing_image(ns):
    (ns["root"] / "images" / "frame_00004.png").unlink()
    with pytest.raises(SceneError, match=r"names the image 'images/frame_00004.png', but .* does not exist"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_nan_matrix(ns):
    _edit(ns["root"], lambda m: m["frames"][0]["transform_matrix"][1].__setitem__(1, float("inf")))
    with pytest.raises(SceneError, match=r"frames\[0\].transform_matrix in .*transforms.json contains NaN or Inf"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_wrong_matrix_shape(ns):
    _edit(ns["root"], lambda m: m["frames"][0].update(transform_matrix=[[1.0, 0.0, 0.0, 0.0]] * 2))
    with pytest.raises(SceneError, match=r"shape \(2, 4\); expected a 4x4"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_three_by_four_matrix_accepted(ns):
    _edit(ns["root"], lambda m: [f.update(transform_matrix=f["transform_matrix"][:3]) for f in m["frames"]])
    scene = load_scene(ns["root"], DataConfig(format="nerfstudio"))
    np.testing.assert_allclose(scene.viewmats[0], opencv_look_at(ns["c2w"][0][:3, 3]), atol=1e-9)


def test_error_unknown_camera_model(ns):
    _edit(ns["root"], lambda m: m.update(camera_model="KANNALA"))
    with pytest.raises(SceneError, match=r"unknown camera_model 'KANNALA' in .*transforms.json.*OPENCV_FISHEYE"):
        load_scene(ns["root"], DataConfig(format="nerfstudio", undistort="crop"))


@pytest.mark.parametrize("model, fix", [("FISHEYE624", "ln -s colmap/sparse .*data.format=colmap"),
                                        ("EQUIRECTANGULAR", "--camera-type equirectangular")])
def test_error_unsupported_camera_model(ns, model, fix):
    _edit(ns["root"], lambda m: m.update(camera_model=model))
    with pytest.raises(SceneError, match=rf"uses camera_model {model}, but only perspective .*{fix}"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_frames_of_different_sizes(ns):
    _edit(ns["root"], lambda m: [f.update(w=20) for f in m["frames"] if f["file_path"].endswith("2.png")])
    with pytest.raises(SceneError, match=r"do not share one size .* 'images/frame_00002.png' at 20x12"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_image_not_matching_w_h(ns):
    iio.imwrite(ns["root"] / "images" / "frame_00003.png", np.zeros((H, W + 3, 3), np.uint8))
    with pytest.raises(SceneError, match=r"frame_00003.png .* is 19x12 but .*transforms.json says it should be 16x12"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_missing_ply(ns):
    _edit(ns["root"], lambda m: m.update(ply_file_path="points.ply"))
    with pytest.raises(SceneError, match=r"names the point cloud 'points.ply', but .* does not exist; correct or "
                                         r"remove \"ply_file_path\""):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_corrupt_ply(ns):
    (ns["root"] / "points.ply").write_text("ply\nformat nonsense\n")
    _edit(ns["root"], lambda m: m.update(ply_file_path="points.ply"))
    with pytest.raises(SceneError, match=r"cannot read the points of .*points.ply"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_invalid_focal(ns):
    _edit(ns["root"], lambda m: m.update(fl_y=-3))
    with pytest.raises(SceneError, match=r"invalid intrinsics"):
        load_scene(ns["root"], DataConfig(format="nerfstudio"))


def test_error_no_transforms_json(tmp_path):
    with pytest.raises(SceneError, match=r"transforms.json does not exist: a nerfstudio scene needs it"):
        load_scene(tmp_path, DataConfig(format="nerfstudio"))


# --- lens distortion: undistorted as COLMAP scenes are --------------------------------------


@pytest.mark.parametrize("cameras", [[("OPENCV", CAMERAS["OPENCV"])], [("OPENCV_FISHEYE", CAMERAS["OPENCV_FISHEYE"])],
                                     [("OPENCV", CAMERAS["OPENCV"]), ("PINHOLE", (50.0, 50.0, 32.0, 24.0))],
                                     [("FULL_OPENCV", CAMERAS["FULL_OPENCV"])]],
                         ids=["opencv", "fisheye", "opencv_and_pinhole", "opencv_with_k3"])
def test_distorted_frames_are_undistorted_like_the_colmap_scene(tmp_path, monkeypatch, cameras):
    """A distorted capture in nerfstudio's layout loads as the same capture in COLMAP's does: the same
    pinhole intrinsics, the same undistorted pixels and poses, and every marker on its point's pinhole
    projection; images_2/ (distorted pixels) is not used."""
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    colmap_root = tmp_path / "colmap"
    distorted_colmap_scene(colmap_root, cameras)
    root = nerfstudio_copy(colmap_root, tmp_path / "ns")
    scene = load_scene(root, DataConfig(format="nerfstudio", holdout_every=0, undistort="crop"))
    reference = load_scene(colmap_root, DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    assert scene.names == tuple(f"images/{n}" for n in reference.names)
    np.testing.assert_allclose(scene.Ks, reference.Ks, rtol=1e-6)
    np.testing.assert_array_equal(scene.images, reference.images)
    np.testing.assert_allclose(scene.viewmats, reference.viewmats, atol=1e-9)
    errors = marker_errors(scene)
    assert len(errors) >= 4 * N_VIEWS and max(errors) < 0.25, max(errors)
    for name in os.listdir(root / "images"):  # distorted pre-downscaled copies must be ignored
        (root / "images_2").mkdir(exist_ok=True)
        iio.imwrite(root / "images_2" / name, np.zeros((H // 2, W // 2, 3), np.uint8))
    half = load_scene(root, DataConfig(format="nerfstudio", holdout_every=0, downscale=2, undistort="crop"))
    np.testing.assert_array_equal(half.images, load_scene(colmap_root, DataConfig(
        format="colmap", holdout_every=0, downscale=2, undistort="crop")).images)
    # data.undistort=mask: the same source-frame images and valid-pixel masks as the COLMAP scene's
    masked = load_scene(root, DataConfig(format="nerfstudio", holdout_every=0, undistort="mask"))
    reference = load_scene(colmap_root, DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    assert masked.valid is not None and masked.valid.shape == reference.valid.shape
    np.testing.assert_array_equal(masked.valid, reference.valid)
    np.testing.assert_array_equal(masked.images, reference.images)
    np.testing.assert_allclose(masked.Ks, reference.Ks, rtol=1e-6)
    # data.undistort=lens: the images as captured with the same lenses as the COLMAP scene's
    kept = load_scene(root, DataConfig(format="nerfstudio", holdout_every=0, undistort="lens"))
    reference = load_scene(colmap_root, DataConfig(format="colmap", holdout_every=0, undistort="lens"))
    assert kept.valid is None and (kept.lens is None) == (reference.lens is None)
    np.testing.assert_array_equal(kept.images, reference.images)
    np.testing.assert_allclose(kept.Ks, reference.Ks, rtol=1e-6)
    if reference.lens is not None:
        assert kept.lens.fisheye == reference.lens.fisheye
        np.testing.assert_allclose(kept.lens.coeffs, reference.lens.coeffs, rtol=1e-6)
        np.testing.assert_allclose(kept.lens.bounds, reference.lens.bounds, rtol=1e-5)


@pytest.mark.parametrize("model, extra, stray", [("OPENCV", dict(k4=0.01), "k4=0.01"),
                                                 ("OPENCV_FISHEYE", dict(p1=0.002), "p1=0.002")])
def test_error_distortion_colmaps_model_does_not_have(tmp_path, model, extra, stray):
    truth = write_nerfstudio_scene(tmp_path / "s", distortion=dict(k1=-0.05, **extra))
    _edit(truth["root"], lambda m: m.update(camera_model=model))
    with pytest.raises(SceneError, match=rf"\(camera_model {model}\) has {stray}, which COLMAP's {model} model does "
                                         r"not have.*data.format=colmap"):
        load_scene(truth["root"], DataConfig(format="nerfstudio", undistort="crop"))


def test_error_distorted_frames_outside_images(tmp_path, monkeypatch):
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    truth = write_nerfstudio_scene(tmp_path / "s", distortion=dict(k1=-0.05, p1=0.001))
    (truth["root"] / "images").rename(truth["root"] / "frames")
    _edit(truth["root"], lambda m: [f.update(file_path=f["file_path"].replace("images/", "frames/"))
                                    for f in m["frames"]])
    with pytest.raises(SceneError, match=r"is distorted and lies outside .*images: COLMAP's undistorter reads"):
        load_scene(truth["root"], DataConfig(format="nerfstudio", undistort="crop"))
