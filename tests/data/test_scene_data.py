"""data/scene_data.py: the one scene type, built in one place, and the settings every layout shares."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.scene_data import check_int_setting, holdout_split, make_scene, split_name

SRC = pathlib.Path(__file__).resolve().parents[2] / "src" / "cusgs_jax"


def test_split_names():
    assert [split_name(n) for n in (0, 2, 3, 8, 11, 12, 21)] == [
        "none", "every_2nd", "every_3rd", "every_8th", "every_11th", "every_12th", "every_21st"]


def test_make_scene_casts_measures_and_checks():
    rng = np.random.default_rng(0)
    viewmats = np.tile(np.eye(4), (3, 1, 1))
    viewmats[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [0, 2, 0]]
    scene = make_scene(path="x", names=["a", "b", "c"], images=np.zeros((3, 5, 7, 3), np.uint8), viewmats=viewmats,
                       Ks=np.tile(np.eye(3), (3, 1, 1)), points=rng.normal(size=(10, 3)),
                       point_colors=np.zeros((10, 3), np.uint8), train_indices=[1, 2], test_indices=[0],
                       dataset_format="colmap", split="every_3rd", background=[1, 1, 1])
    assert (scene.width, scene.height, scene.names, scene.background) == (7, 5, ("a", "b", "c"), (1.0, 1.0, 1.0))
    assert scene.viewmats.dtype == np.float64 and scene.Ks.dtype == np.float32
    assert scene.train_indices.dtype == np.int32 and scene.path == pathlib.Path("x")
    centres = -viewmats[:, :3, 3]
    assert scene.extent == pytest.approx(1.1 * np.max(np.linalg.norm(centres - centres.mean(0), axis=1)))
    with pytest.raises(SceneError, match="splat.background"):
        make_scene(path="x", names=["a"], images=np.zeros((1, 5, 7, 3), np.uint8), viewmats=viewmats[:1],
                   Ks=np.eye(3)[None], points=np.zeros((1, 3)), point_colors=np.zeros((1, 3), np.uint8),
                   train_indices=[0], test_indices=[], dataset_format="colmap", split="none", background=[2, 0, 0])


def test_shared_settings_and_split():
    assert check_int_setting("data.downscale", 2.0, minimum=1) == 2
    with pytest.raises(SceneError, match=r"data.downscale=0 must be an integer >= 1"):
        check_int_setting("data.downscale", 0, minimum=1)
    train, test = holdout_split(9, 4, pathlib.Path("s"))
    assert test.tolist() == [0, 4, 8] and train.tolist() == [1, 2, 3, 5, 6, 7]
    with pytest.raises(SceneError, match="holds out all 1 image"):
        holdout_split(1, 1, pathlib.Path("s"))


def test_scene_data_is_constructed_in_one_module_and_no_layout_imports_a_private_name():
    constructed = [p.relative_to(SRC).as_posix() for p in SRC.rglob("*.py") if "SceneData(" in p.read_text()]
    assert constructed == ["data/scene_data.py"]
    private = [(p.name, line.strip()) for p in (SRC / "data").glob("*.py") for line in p.read_text().splitlines()
               if line.startswith("from cusgs_jax.") and " import " in line
               and any(name.strip().startswith("_") for name in line.split(" import ", 1)[1].strip("()").split(","))]
    assert not private, private
