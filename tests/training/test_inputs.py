"""What a run reads (training/inputs.py): any layout loads in the normalised frame with the background resolved;
feature targets keep every value float16 cannot hold; images smaller than the SSIM window are refused at load;
feature targets far larger than the extractors' are warned about; the view order is a permutation per epoch."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.config import Config, DataConfig
from cusgs_jax.compose import compose_config
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.features import FeatureSet
from cusgs_jax.training.inputs import (FLOAT16_MAX, feature_targets, load_data, load_feature_targets,
                                       mask_feature_maps, resolve_background, view_order)
from cusgs_jax.testing.transforms_scenes import write_blender_scene


class _Maps:
    def __init__(self, maps):
        self.maps = maps


def test_feature_targets_are_float16_unless_a_value_would_overflow_it():
    small = np.random.default_rng(0).normal(size=(3, 4, 5, 2)).astype(np.float32)
    large = small.copy()
    large[1, 2, 3, 0] = 1e5  # beyond float16's 65504: would become inf
    targets = feature_targets({"small": _Maps(small), "large": _Maps(large)}, np.array([0, 1]))
    assert targets["small"].dtype == np.float16 and targets["large"].dtype == np.float32
    assert np.all(np.isfinite(np.asarray(targets["large"]))) and float(np.max(targets["large"])) == 1e5
    np.testing.assert_array_equal(np.asarray(targets["large"]), large[[0, 1]])
    assert FLOAT16_MAX == 65504.0


def test_images_smaller_than_the_ssim_window_are_refused_at_load_naming_the_fix(demo, tmp_path):
    from cusgs_jax.testing.scenes import object_scene

    scene, _ = load_data(compose_config([f"data.path={demo}", "data.downscale=2", "features=none"]))
    assert (scene.width, scene.height) == (20, 15)  # 40x30 / 2: large enough
    with pytest.raises(SceneError, match=r"demo.*: its images load at 10x8 pixels with data\.downscale=4, smaller "
                                         r"than the 11x11 pixels .*SSIM.*use a smaller data\.downscale "
                                         r"\(e\.g\. data\.downscale=2\)"):
        load_data(compose_config([f"data.path={demo}", "data.downscale=4", "features=none"]))
    tiny = object_scene(tmp_path / "tiny", views=4, width=8, height=8, num_points=50)
    with pytest.raises(SceneError, match=r"8x8 pixels with data\.downscale=1.*images of at least 11x11 pixels"):
        load_data(compose_config([f"data.path={tiny}", "features=none"]))


@pytest.mark.parametrize("damage", ["one_value", "every_map"])
def test_feature_targets_far_larger_than_the_extractors_give_are_warned_about_at_load(demo, tmp_path, caplog,
                                                                                       damage):
    import shutil

    from cusgs_jax.data.features import feature_dir
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.extract import ensure_extracted

    scene_dir = tmp_path / "scene"
    shutil.copytree(demo, scene_dir)
    ensure_extracted(load_scene(scene_dir, DataConfig(holdout_every=0)), "semantic", progress=False)
    cfg = compose_config([f"data.path={scene_dir}", "features.models=[{name: semantic}]"])
    scene, _ = load_data(cfg)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        load_feature_targets(cfg.features.resolve(demo_scene=False), scene, 0)
    assert "target vectors" not in caplog.text  # the extractor's own maps: unit vectors
    files = sorted(feature_dir(scene_dir, "semantic").glob("*.npy"))
    for i, f in enumerate(files):
        maps = np.load(f).astype(np.float32)
        if damage == "every_map":
            maps *= 1e5
        elif i == 2:
            maps[3, 4, 0] = 1e6
        np.save(f, maps)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        load_feature_targets(cfg.features.resolve(demo_scene=False), scene, 0)
    assert "feature model semantic: target vectors in" in caplog.text and "re-extract" in caplog.text
    if damage == "one_value":
        assert "norms 1 to 1e+06 (median 1); 1 of " in caplog.text and files[2].name in caplog.text
    else:
        assert "norms 1e+05 to 1e+05" in caplog.text


def test_demo_lens_scene_is_generated_and_undistorted(tmp_path, monkeypatch):
    """data.demo.lens=opencv: the demo through the lens, generated into the cache and undistorted on load."""
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path))
    cfg = compose_config(["data.demo.lens=opencv", "data.demo.views=3", "data.demo.width=48", "data.demo.height=36",
                          "data.undistort=crop"])
    scene, _ = load_data(cfg)
    assert (tmp_path / "demo-lens4-opencv-s0-v3-48x36" / "scene.json").is_file()
    assert (tmp_path / "demo-lens4-opencv-s0-v3-48x36" / "lens" / "object_ids").is_dir()  # maps for data.undistort=lens
    assert (tmp_path / "undistorted").is_dir() and scene.width < 48 and scene.height < 36


def test_a_blender_scene_loads_on_white_and_the_background_resolves_to_it(tmp_path, demo):
    write_blender_scene(tmp_path / "b")
    cfg = Config(data=DataConfig(path=str(tmp_path / "b"), random_points=300))
    scene, world = load_data(cfg)
    assert scene.dataset_format == "blender" and scene.extent == 1.0 and len(scene.points) == scene.carving.kept
    assert scene.carving.points == 300
    assert np.all(scene.images[:, 0, 0] == 255)
    assert resolve_background(cfg, scene).splat.background == (1.0, 1.0, 1.0)
    black = cfg.replace(splat=dict(background=(0.0, 0.0, 0.0)))  # set explicitly: kept
    scene_black, _ = load_data(black)
    assert np.all(scene_black.images[:, 0, 0] == 0)
    assert resolve_background(black, scene_black).splat.background == (0.0, 0.0, 0.0)
    demo_cfg = Config(data=DataConfig(path=str(demo)))
    scene_c, _ = load_data(demo_cfg)
    assert resolve_background(demo_cfg, scene_c).splat.background == (0.0, 0.0, 0.0)
    with pytest.raises(SceneError, match="transforms.json does not exist"):
        load_data(Config(data=DataConfig(path=str(demo), format="nerfstudio")))


def test_view_order_is_a_permutation_per_epoch():
    seq = [view_order(3, 7, s) for s in range(14)]
    assert sorted(seq[:7]) == list(range(7)) and sorted(seq[7:]) == list(range(7))
    assert seq == [view_order(3, 7, s) for s in range(14)]
    assert seq[:7] != seq[7:]  # a fresh permutation per epoch


def test_mask_feature_maps_zeroes_the_vectors_of_invalid_pixels():
    """A feature pixel reads the image pixel nearest its centre, as the loss samples it."""
    maps = np.arange(2 * 3 * 4 * 2, dtype=np.float32).reshape(2, 3, 4, 2) + 1.0
    fs = FeatureSet("m", maps, np.ones((2, 3, 4), bool), 2, (4, 3), {})
    valid = np.ones((2, 6, 8), bool)
    valid[0, :2, :2] = False  # image pixels under feature pixel (0, 0) of view 0
    valid[1, 5, 7] = False  # under feature pixel (2, 3) of view 1
    out = mask_feature_maps(fs, valid)
    zero = np.zeros((2, 3, 4), bool)
    zero[0, 0, 0] = zero[1, 2, 3] = True
    assert np.all(out.maps[zero] == 0) and np.array_equal(out.maps[~zero], maps[~zero])
    assert np.array_equal(out.valid, ~zero)


def _distorted_daisy_run(tmp_path, monkeypatch, model, mode):
    """(scene folder, config, loaded scene) of a tiny distorted scene with daisy features, data.undistort=mode."""
    from cusgs_jax.testing.distorted_scenes import CAMERAS, distorted_colmap_scene

    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    root = tmp_path / "s"
    distorted_colmap_scene(root, [(model, CAMERAS[model])])
    cfg = compose_config([f"data.path={root}", f"data.undistort={mode}", "data.holdout_every=0",
                          "features.models=[{name: daisy}]"])
    return root, cfg, load_data(cfg)[0]


def test_a_masked_scene_zeroes_its_invalid_feature_targets_and_refuses_features_of_the_other_mode(tmp_path, monkeypatch):
    root, cfg, scene = _distorted_daisy_run(tmp_path, monkeypatch, "SIMPLE_RADIAL", "mask")
    assert scene.valid is not None and 0 < (~scene.valid).mean() < 0.3
    maps, banks = load_feature_targets(cfg.features, scene, 0)  # extracts from the masked images
    fs = maps["daisy"]
    assert fs.meta["undistort"] == "mask"
    assert fs.maps.shape[1:3] == scene.valid.shape[1:]  # daisy: one vector per image pixel
    assert np.all(fs.maps[~scene.valid] == 0) and np.all(np.any(fs.maps[scene.valid] != 0, axis=-1))
    crop = compose_config([f"data.path={root}", "data.undistort=crop", "data.holdout_every=0",
                           "features.models=[{name: daisy}]"])
    crop_scene, _ = load_data(crop)
    with pytest.raises(SceneError, match=r"daisy features .* data\.undistort=mask, but this run uses "
                                         r"data\.undistort=crop: re-extract them \(cusgs-extract .* --undistort crop"):
        load_feature_targets(crop.features, crop_scene, 0)


def test_a_lens_scene_takes_features_of_its_images_as_captured_and_refuses_the_others(tmp_path, monkeypatch):
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.extract import extract_scene

    root, cfg, scene = _distorted_daisy_run(tmp_path, monkeypatch, "OPENCV", "lens")
    assert scene.lens is not None and scene.valid is None
    maps, _ = load_feature_targets(cfg.features, scene, 0)  # auto-extracted from the images as captured
    fs = maps["daisy"]
    assert fs.meta["undistort"] == "lens" and fs.maps.shape[1:3] == (scene.height, scene.width)
    cropped = load_scene(root, DataConfig(holdout_every=0, random_points=2, carve="none", undistort="crop"))
    direct = extract_scene(cropped, "daisy", overwrite=True, progress=False)  # crop-frame features
    assert direct.num_views == scene.num_images
    with pytest.raises(SceneError, match=r"daisy features .* data\.undistort=crop, but this run uses "
                                         r"data\.undistort=lens: re-extract them \(cusgs-extract .* --undistort lens"):
        load_feature_targets(cfg.features, scene, 0)
