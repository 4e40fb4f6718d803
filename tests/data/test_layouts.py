"""Scene layouts (data/layouts.py): detection, dispatch, background defaults, data.format, COLMAP equivalence."""

from __future__ import annotations

import math

import imageio.v3 as iio
import numpy as np
import pytest

from cusgs_jax.config import DataConfig, SplatConfig
from cusgs_jax.compose import compose_config
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.layouts import default_background, detect_format, read_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.errors import ConfigError
from cusgs_jax.testing.transforms_scenes import opencv_look_at, write_blender_scene, write_nerfstudio_scene


@pytest.fixture(scope="module")
def colmap(tmp_path_factory):
    return generate_demo_scene(tmp_path_factory.mktemp("colmap") / "demo", num_views=4, width=24, height=18,
                               num_points=200)


def test_detect_each_layout(tmp_path, colmap):
    write_blender_scene(tmp_path / "b")
    write_nerfstudio_scene(tmp_path / "n")
    assert detect_format(tmp_path / "b") == "blender"
    assert detect_format(tmp_path / "n") == "nerfstudio"
    assert detect_format(colmap) == "colmap"


def test_detect_prefers_colmap_over_transforms_json(tmp_path, colmap, caplog):
    import shutil

    both = tmp_path / "both"
    shutil.copytree(colmap, both)
    write_nerfstudio_scene(both)
    with caplog.at_level("INFO", logger="cusgs_jax"):
        assert detect_format(both) == "colmap"
    assert "data.format=nerfstudio" in caplog.text
    assert load_scene(both, DataConfig(format="nerfstudio", holdout_every=0)).dataset_format == "nerfstudio"


def test_detect_nothing_recognisable(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(SceneError, match=rf"no scene layout recognised in {tmp_path} \(it holds images/, notes.txt\)"
                                         r".*COLMAP scene .*Blender .*nerfstudio"):
        detect_format(tmp_path)


def test_detect_missing_folder_and_file(tmp_path):
    with pytest.raises(SceneError, match=r"does not exist: set data.path to a COLMAP scene"):
        detect_format(tmp_path / "nope")
    (tmp_path / "f").write_text("")
    with pytest.raises(SceneError, match=r"is a file, not a folder"):
        detect_format(tmp_path / "f")
    with pytest.raises(SceneError, match=r"data.path is empty"):
        read_scene("", DataConfig())  # load_scene("") is the demo scene (data/loader.py::scene_folder)


def test_dispatch_and_split_and_background_defaults(tmp_path, colmap):
    write_blender_scene(tmp_path / "b")
    write_nerfstudio_scene(tmp_path / "n")
    b = load_scene(tmp_path / "b", DataConfig(holdout_every=3, random_points=100))
    n = load_scene(tmp_path / "n", DataConfig(holdout_every=3, random_points=100))
    c = load_scene(colmap, DataConfig(holdout_every=3))
    assert (b.dataset_format, b.split, b.background) == ("blender", "transforms_test", (1.0, 1.0, 1.0))
    assert (n.dataset_format, n.split, n.background) == ("nerfstudio", "every_3rd", (0.0, 0.0, 0.0))
    assert (c.dataset_format, c.split, c.background) == ("colmap", "every_3rd", (0.0, 0.0, 0.0))
    np.testing.assert_array_equal(b.test_indices, [4, 5])  # holdout_every does not apply to Blender
    assert b.carving.points == n.carving.points == 100  # drawn, then carved by the training frusta (data/carve.py)
    assert (len(b.points), len(n.points)) == (b.carving.kept, n.carving.kept)
    red = load_scene(tmp_path / "b", DataConfig(random_points=100), background=(1.0, 0.0, 0.0))
    assert red.background == (1.0, 0.0, 0.0) and np.all(red.images[:, 0, 0] == [255, 0, 0])
    assert load_scene(colmap, DataConfig(holdout_every=0)).split == "none"
    assert default_background("blender") == (1.0, 1.0, 1.0) and default_background("colmap") == (0.0, 0.0, 0.0)


def test_explicit_format_of_the_wrong_layout(tmp_path, colmap):
    write_nerfstudio_scene(tmp_path / "n")
    with pytest.raises(SceneError, match=r"transforms_train.json does not exist: a Blender"):
        load_scene(tmp_path / "n", DataConfig(format="blender"))
    with pytest.raises(SceneError, match=r"no COLMAP model folder"):
        load_scene(tmp_path / "n", DataConfig(format="colmap"))
    with pytest.raises(SceneError, match=r"transforms.json does not exist: a nerfstudio scene"):
        load_scene(colmap, DataConfig(format="nerfstudio"))
    with pytest.raises(ConfigError, match=r"data.format='llff': must be auto or one of colmap, blender, nerfstudio"):
        load_scene(colmap, DataConfig(format="llff"))


def test_blender_scene_has_the_cameras_of_the_equivalent_colmap_scene(tmp_path):
    """The same cameras written as a Blender scene and as a COLMAP model (PINHOLE f, W/2, H/2; poses from an
    OpenCV look-at, built independently of the OpenGL ones) load to the same viewmats and Ks."""
    pycolmap = pytest.importorskip("pycolmap")

    W, H = 16, 12
    truth = write_blender_scene(tmp_path / "blender", width=W, height=H, rgba=False, with_val=False)
    f = 0.5 * W / math.tan(0.5 * truth["angle_x"])
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model="PINHOLE", width=W, height=H,
                                                    params=[f, f, W / 2, H / 2]))
    keypoints = np.random.default_rng(0).uniform(0, 10, (3, 2))
    for iid, (name, c2w, pixels) in enumerate(zip(truth["names"], truth["c2w"], truth["images"]), start=1):
        view = opencv_look_at(c2w[:3, 3])
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=iid)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(view[:3, :3]), view[:3, 3]))
        (tmp_path / "colmap" / "images" / name).parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(tmp_path / "colmap" / "images" / name, pixels)
    for p in range(3):
        track = pycolmap.Track()
        for iid in range(1, len(truth["names"]) + 1):
            track.add_element(iid, p)
        rec.add_point3D(np.zeros(3) + p * 0.1, track, np.zeros(3, np.uint8))
    (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
    rec.write(str(tmp_path / "colmap" / "sparse" / "0"))

    blender = load_scene(tmp_path / "blender", DataConfig(random_points=100))
    col = load_scene(tmp_path / "colmap", DataConfig(format="colmap", holdout_every=0))
    order = [col.names.index(name) for name in blender.names]
    np.testing.assert_allclose(blender.viewmats, col.viewmats[order], atol=1e-6)
    np.testing.assert_allclose(blender.Ks, col.Ks[order], rtol=1e-6)
    np.testing.assert_array_equal(blender.images, col.images[order])
    assert (blender.width, blender.height) == (col.width, col.height)
    np.testing.assert_allclose(blender.camera_centers, col.camera_centers[order], atol=1e-6)


# --- configuration and the app's loading ------------------------------------------------------


def test_data_format_setting_is_validated():
    assert DataConfig().format == "auto" and DataConfig(format="blender").format == "blender"
    with pytest.raises(ConfigError, match=r"data.format='llff': must be auto or one of colmap, blender, nerfstudio"):
        DataConfig(format="llff")
    with pytest.raises(ConfigError, match=r"data.random_points"):
        DataConfig(random_points=0)
    assert compose_config(["data.format=nerfstudio"]).data.format == "nerfstudio"


def test_background_not_set_is_none_and_renders_black():
    assert SplatConfig().background is None and SplatConfig().background_color == (0.0, 0.0, 0.0)
    assert SplatConfig(background=(1, 1, 1)).background_color == (1.0, 1.0, 1.0)
    assert compose_config([]).splat.background is None
    assert compose_config(["splat.background=[1,1,1]"]).splat.background == (1.0, 1.0, 1.0)
