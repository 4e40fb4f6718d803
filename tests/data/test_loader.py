"""data/loader.py: ``load_scene(path, data)`` is the scene ``cusgs-train data.path=path`` trains on, in every
layout and camera frame, and ``cusgs_jax.load_scene(path)`` with no settings is the one the CLI's defaults load."""

from __future__ import annotations

import numpy as np
import pytest

import cusgs_jax
from cusgs_jax.config import DataConfig
from cusgs_jax.compose import compose_config
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.loader import load_cameras, load_scene, scene_folder
from cusgs_jax.data.normalize import normalize_scene
from cusgs_jax.training.inputs import load_data
from cusgs_jax.testing.distorted_scenes import CAMERAS, distorted_colmap_scene
from cusgs_jax.testing.transforms_scenes import write_blender_scene, write_nerfstudio_scene


def _same(a, b):
    assert (a.names, a.width, a.height, a.dataset_format, a.split, a.camera_frame, a.background) == \
           (b.names, b.width, b.height, b.dataset_format, b.split, b.camera_frame, b.background)
    for key in ("images", "viewmats", "Ks", "points", "train_indices", "test_indices"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert (a.valid is None) == (b.valid is None) and (a.lens is None) == (b.lens is None)
    if a.valid is not None:
        np.testing.assert_array_equal(a.valid, b.valid)


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    """Undistorted images cache into the test's own folder, never ~/.cache."""
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("layouts")
    distorted_colmap_scene(root / "lens", [("OPENCV", CAMERAS["OPENCV"])])
    write_blender_scene(root / "blender", width=24, height=18)
    write_nerfstudio_scene(root / "nerfstudio", width=24, height=18)
    return dict(pinhole=generate_demo_scene(root / "pinhole", num_views=5, width=32, height=24, num_points=300),
                lens=root / "lens", blender=root / "blender", nerfstudio=root / "nerfstudio")


@pytest.mark.parametrize("layout,extra", [("pinhole", []), ("lens", ["data.undistort=crop"]),
                                          ("lens", ["data.undistort=mask"]), ("lens", ["data.undistort=lens"]),
                                          ("blender", []), ("nerfstudio", ["data.holdout_every=3"])])
def test_the_library_loads_the_scene_the_cli_trains_on(scenes, cache_dir, layout, extra):
    path = scenes[layout]
    cfg = compose_config([f"data.path={path}", "data.random_points=500", *extra])  # what cusgs-train composes
    trained, world = load_data(cfg)  # what cusgs-train's setup trains on (normalised frame)
    library, library_world = normalize_scene(load_scene(path, cfg.data, seed=cfg.train.seed), align=cfg.data.align)
    _same(library, trained)
    assert library_world.as_dict() == world.as_dict()


@pytest.mark.parametrize("layout", ["pinhole", "lens", "blender"])
def test_no_settings_means_the_cli_defaults(scenes, cache_dir, layout):
    """``cusgs_jax.load_scene(path)`` = ``cusgs-train data.path=path``'s scene (before normalisation): the same
    defaults, e.g. distorted cameras kept and rendered through their lens (data.undistort=lens)."""
    path = scenes[layout]
    plain = cusgs_jax.load_scene(path)
    trained, world = load_data(compose_config([f"data.path={path}"]))
    _same(normalize_scene(plain, align=DataConfig().align)[0], trained)
    assert plain.camera_frame == ("lens" if layout == "lens" else "crop")


def test_no_path_is_the_configured_demo_and_a_path_wins_over_data_path(scenes, tmp_path):
    data = DataConfig(path=str(scenes["blender"]))
    assert scene_folder(scenes["pinhole"], data) == scenes["pinhole"]
    assert load_scene(scenes["pinhole"], data).dataset_format == "colmap"
    assert load_scene(None, data).dataset_format == "blender"
    assert scene_folder(None, DataConfig(), generate=False).name.startswith("demo")


@pytest.mark.parametrize("layout,undistort", [("pinhole", "lens"), ("lens", "crop"), ("lens", "mask"), ("lens", "lens"),
                                              ("blender", "lens"), ("nerfstudio", "lens")])
def test_load_cameras_are_the_scenes_cameras_without_reading_an_image(scenes, cache_dir, layout, undistort):
    data = DataConfig(undistort=undistort, holdout_every=3, random_points=100)
    cameras = load_cameras(scenes[layout], data)
    assert not cache_dir.exists()  # nothing undistorted (nor any image read) for the cameras alone
    scene = load_scene(scenes[layout], data)
    for key in ("viewmats", "Ks", "train_indices", "test_indices"):
        np.testing.assert_array_equal(getattr(cameras, key), getattr(scene, key), err_msg=key)
        assert getattr(cameras, key).dtype == getattr(scene, key).dtype
    assert (cameras.width, cameras.height) == (scene.width, scene.height)
    assert (cameras.lens is None) == (scene.lens is None)


def test_data_that_is_not_a_data_config_is_a_type_error_saying_what_to_pass(tmp_path):
    from cusgs_jax.config import Config

    with pytest.raises(TypeError, match="got dict: build one with DataConfig"):
        load_scene(tmp_path, data={"downscale": 2})
    with pytest.raises(TypeError, match="got Config: pass cfg.data"):
        load_scene(tmp_path, data=Config())


@pytest.mark.parametrize("seed, error, match", [
    ("a", TypeError, r"seed must be a non-negative int \(train.seed.*got str 'a'"),
    (1.5, TypeError, r"seed must be a non-negative int .*got float 1.5"),
    (True, TypeError, r"seed must be a non-negative int .*got bool"),
    (-1, ValueError, r"seed must be a non-negative int \(train.seed\), got -1"),
])
def test_a_seed_that_is_not_a_non_negative_int_is_named(scenes, seed, error, match):
    with pytest.raises(error, match=match):
        load_scene(scenes["pinhole"], seed=seed)


def test_a_numpy_integer_seed_loads_as_the_int_would(scenes):
    data = DataConfig(random_points=50)
    three = load_scene(scenes["blender"], data, seed=3)
    _same(load_scene(scenes["blender"], data, seed=np.int64(3)), three)
    assert not np.array_equal(load_scene(scenes["blender"], data, seed=4).points, three.points)  # the seed counts
