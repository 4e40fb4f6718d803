"""data/finish.py: the pass every layout's RawScene goes through (settings, names, one size, intrinsics,
split, background, points) — on hand-made RawScenes, and through the three readers."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.finish import check_settings, default_background, existing_folder, finish_cameras, finish_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.raw import RawScene, Split, ViewCamera
from cusgs_jax.errors import ConfigError

V = 6


def _raw(**overrides) -> RawScene:
    """Six views on a circle looking at the origin, 40×30 images of their index, no points."""
    viewmats = []
    for i in range(V):
        angle = 2 * np.pi * i / V
        center = np.array([3 * np.cos(angle), 0.0, 3 * np.sin(angle)])
        forward = -center / np.linalg.norm(center)
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        view = np.eye(4)
        view[:3, :3] = np.stack([right, down, forward])
        view[:3, 3] = -view[:3, :3] @ center
        viewmats.append(view)
    seen = {}

    def read_images(background):
        seen["background"] = background
        return np.stack([np.full((30, 40, 3), i, np.uint8) for i in range(V)])

    fields = dict(folder=pathlib.Path("/scene"), dataset_format="nerfstudio", names=tuple(f"v{i}.png" for i in range(V)),
                  viewmats=np.stack(viewmats), cameras=(ViewCamera(50.0, 52.0, 20.0, 15.0, 40, 30),) * V,
                  views_source="transforms.json", cameras_source="transforms.json", size_fix="resize them",
                  read_images=read_images)
    fields.update(overrides)
    return RawScene(**fields), seen


def test_intrinsics_split_background_and_random_points():
    raw, seen = _raw()
    data = check_settings(DataConfig(holdout_every=3, random_points=50, carve="none"))
    scene = finish_scene(raw, data, seed=1)
    np.testing.assert_allclose(scene.Ks[0], [[50, 0, 20], [0, 52, 15], [0, 0, 1]])
    assert scene.test_indices.tolist() == [0, 3] and scene.split == "every_3rd"
    assert seen["background"] == (0.0, 0.0, 0.0) == scene.background  # nerfstudio's default: black
    assert scene.points.shape == (50, 3) and scene.random_points == "cube_and_rays"  # auto for nerfstudio
    again = finish_scene(_raw()[0], data, seed=1)
    np.testing.assert_array_equal(again.points, scene.points)  # the seed draws them
    assert scene.images[4, 0, 0, 0] == 4 and (scene.width, scene.height) == (40, 30)


def test_random_points_are_carved_by_the_training_frusta_and_the_record_says_so(caplog):
    data = check_settings(DataConfig(holdout_every=3, random_points=400, random_init="cube"))
    every = finish_scene(_raw()[0], dataclasses.replace(data, carve="none"), seed=1)
    carved = finish_scene(_raw()[0], data, seed=1)
    assert every.carving is None and len(every.points) == 400
    record = carved.carving
    assert record.points == 400 and record.kept == len(carved.points) and record.views_with_alpha == 0
    assert record.outside_frusta == 400 - record.kept > 0 and record.transparent == 0
    kept = (every.points[:, None, :] == carved.points[None]).all(-1).any(0)
    assert kept.all()  # a subset of the same draw, in its order
    clear = [np.zeros((30, 40), bool)] * V  # alpha 0 everywhere: every view named and ignored, the frusta carve
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        blank = finish_scene(_raw(read_coverage=lambda: clear)[0], data, seed=1)
    assert blank.carving.ignored_views == ("v1.png", "v2.png", "v4.png", "v5.png")  # the training views
    assert blank.carving.views_with_alpha == 0 and blank.carving.transparent == 0
    np.testing.assert_array_equal(blank.points, carved.points)  # as without alpha
    assert "v1.png, v2.png, v4.png, v5.png" in caplog.text and "blank" in caplog.text
    corner = [np.pad(np.ones((2, 2), bool), ((0, 28), (0, 38)))] * V  # coverage nowhere near the points
    few = dataclasses.replace(data, random_points=40)
    with pytest.raises(SceneError, match="left 0 of 40 .*alpha is not coverage.*data.carve=none"):
        finish_scene(_raw(read_coverage=lambda: corner)[0], few, seed=1)


def test_scene_points_are_never_carved():
    points, colors = np.random.default_rng(0).normal(size=(30, 3)) * 50, np.zeros((30, 3), np.uint8)
    scene = finish_scene(_raw(points=points, point_colors=colors)[0], check_settings(DataConfig()))
    assert scene.carving is None
    np.testing.assert_array_equal(scene.points, points)  # bit for bit, even those no view sees


def test_downscale_divides_the_intrinsics_and_the_size():
    raw, _ = _raw(read_images=lambda bg: np.zeros((V, 15, 20, 3), np.uint8))
    cameras = finish_cameras(raw, check_settings(DataConfig(downscale=2)))
    np.testing.assert_allclose(cameras.Ks[0], [[25, 0, 10], [0, 26, 7.5], [0, 0, 1]])
    assert (cameras.width, cameras.height) == (20, 15)


def test_a_layouts_own_split_and_points_and_background_are_kept():
    points, colors = np.ones((5, 3)), np.full((5, 3), 7, np.uint8)
    split = Split(np.arange(4, dtype=np.int32), np.array([4, 5], np.int32), "transforms_test")
    raw, seen = _raw(dataset_format="blender", split=split, points=points, point_colors=colors)
    scene = finish_scene(raw, check_settings(DataConfig(holdout_every=2)))
    assert scene.test_indices.tolist() == [4, 5] and scene.split == "transforms_test"
    assert scene.random_points is None and scene.points.shape == (5, 3)
    assert seen["background"] == default_background("blender") == (1.0, 1.0, 1.0)
    red = finish_scene(raw, check_settings(DataConfig()), background=(1.0, 0.0, 0.0))
    assert red.background == (1.0, 0.0, 0.0)


def test_differing_sizes_and_duplicate_names_are_refused_naming_the_file_and_views():
    cameras = (ViewCamera(50.0, 50.0, 20.0, 15.0, 40, 30),) * (V - 1) + (ViewCamera(50.0, 50.0, 22.0, 15.0, 44, 30),)
    raw, _ = _raw(cameras=cameras)
    with pytest.raises(SceneError, match=r"the images of transforms.json do not share one size with data.downscale=1: "
                                         r"'v0.png' loads at 40x30 but 'v5.png' at 44x30; .* — resize them"):
        finish_scene(raw, check_settings(DataConfig()))
    raw, seen = _raw(names=("a.png",) * V)
    with pytest.raises(SceneError, match=r"two views of transforms.json use the same image 'a.png'"):
        finish_scene(raw, check_settings(DataConfig()))
    assert not seen  # refused before any image was read


def test_settings_are_checked_as_scene_errors_naming_the_option(tmp_path):
    assert check_settings(DataConfig(downscale=2.0)).downscale == 2
    with pytest.raises(SceneError, match=r"data.downscale=1.5 must be an integer >= 1"):
        check_settings(DataConfig(downscale=1.5))
    with pytest.raises(SceneError, match=r"data.downscale=1.5 must be an integer >= 1"):
        load_scene(tmp_path, DataConfig(downscale=1.5))  # checked before the folder is looked at
    with pytest.raises(ConfigError, match=r"data.holdout_every=-1: must be a number >= 0"):
        load_scene(tmp_path, DataConfig(holdout_every=-1))
    with pytest.raises(ConfigError, match=r"data.undistort='blur'"):
        load_scene(tmp_path, DataConfig(undistort="blur"))
    assert dataclasses.asdict(check_settings(DataConfig(downscale=4))) == dataclasses.asdict(DataConfig(downscale=4))


def test_existing_folder(tmp_path):
    assert existing_folder(tmp_path) == tmp_path
    with pytest.raises(SceneError, match=r"data.path is empty: set it to a COLMAP scene"):
        existing_folder("")
    with pytest.raises(SceneError, match=r"nope does not exist: set data.path to"):
        existing_folder(tmp_path / "nope")
    (tmp_path / "f").write_text("x")
    with pytest.raises(SceneError, match=r"is a file, not a folder"):
        existing_folder(tmp_path / "f")
