"""The object-centric demo capture (cusgs_jax.data.demo.objects) on a tiny version: 14 views at 32x24."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.demo.objects import OBJECTS, composite_white, generate_object_scenes


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("objects")
    return generate_object_scenes(out, num_views=14, holdout_every=7, width=32, height=24, num_points=800)


def test_split_and_layout(tiny):
    assert tiny["test"] == [0, 7] and len(tiny["train"]) == 12
    train = json.loads((tiny["blender"] / "transforms_train.json").read_text())
    test = json.loads((tiny["blender"] / "transforms_test.json").read_text())
    assert [f["file_path"] for f in test["frames"]] == ["./test/r_000", "./test/r_007"]
    assert len(train["frames"]) == 12
    rgba = iio.imread(tiny["blender"] / "test" / "r_000.png")
    assert rgba.shape == (24, 32, 4)
    alpha = rgba[..., 3]
    assert (alpha == 0).any() and (alpha == 255).any()  # background is transparent, objects opaque
    assert (alpha[0] == 0).all() and (alpha[-1] == 0).all()  # no floor or walls around the objects


def test_both_loaders_agree(tiny):
    """The Blender and the COLMAP folder give the same cameras, images and held-out views."""
    b = load_scene(tiny["blender"], DataConfig(format="blender", random_points=100))
    c = load_scene(tiny["colmap"], DataConfig(format="colmap", holdout_every=7), background=(1.0, 1.0, 1.0))
    order = tiny["train"] + tiny["test"]  # Blender lists train frames then test frames
    assert list(b.names) == [f"{s}/r_{k:03d}.png" for s, ks in (("train", tiny["train"]), ("test", tiny["test"]))
                             for k in ks]
    assert list(c.names) == [f"view_{k:03d}.png" for k in range(14)]
    np.testing.assert_allclose(b.viewmats, c.viewmats[order], atol=1e-9)
    np.testing.assert_allclose(b.Ks, c.Ks[order], rtol=1e-6)
    np.testing.assert_array_equal(b.images, c.images[order])
    assert [c.names[i] for i in c.test_indices] == ["view_000.png", "view_007.png"]
    assert [b.names[i] for i in b.test_indices] == ["test/r_000.png", "test/r_007.png"]
    # the white composite is not a no-op: some pixels are partly covered
    rgba = iio.imread(tiny["blender"] / "test" / "r_000.png")
    assert not np.array_equal(composite_white(rgba), rgba[..., :3])


def test_points_lie_on_objects(tiny):
    """The COLMAP points project onto pixels that see an object (alpha > 0): all but a few at silhouettes of
    the thin table and chair legs (under half a pixel wide at this size), against ~20 % coverage by chance."""
    c = load_scene(tiny["colmap"], DataConfig(format="colmap", holdout_every=7), background=(1.0, 1.0, 1.0))
    assert len(c.points) > 100
    hits, total = 0, 0
    for v in range(len(c.names)):
        alpha = iio.imread(tiny["blender"] / ("test" if v % 7 == 0 else "train") / f"r_{v:03d}.png")[..., 3]
        pc = c.points @ c.viewmats[v, :3, :3].T + c.viewmats[v, :3, 3]
        uv = pc[:, :2] / pc[:, 2:] * np.diag(c.Ks[v])[:2] + c.Ks[v, :2, 2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 32) & (uv[:, 1] >= 0) & (uv[:, 1] < 24) & (pc[:, 2] > 0)
        col, row = np.floor(uv[inside]).astype(int).T
        hits += int((alpha[row, col] > 0).sum())
        total += int(inside.sum())
    assert total > 0 and hits >= 0.95 * total
    assert set(OBJECTS) >= {"table_top", "chair"}


def test_carving_keeps_every_surface_point_and_drops_most_random_points(tiny):
    """The Blender layout's alpha carves its random start (data/carve.py); the COLMAP layout's SfM-style
    surface points of the same objects, in the same world frame, all survive the same carving."""
    from cusgs_jax.data.blender import read_blender
    from cusgs_jax.data.carve import carve
    from cusgs_jax.data.finish import check_settings, finish_cameras, finish_scene

    data = check_settings(DataConfig(random_points=5000))
    raw = read_blender(tiny["blender"], data)
    scene = finish_scene(raw, data)
    coverage = raw.read_coverage()
    assert scene.carving.views_with_alpha == 12 and len(coverage) == 14
    assert scene.carving.kept == len(scene.points) < 0.5 * 5000  # most of the cube is empty space
    cameras = finish_cameras(raw, data)
    surface = load_scene(tiny["colmap"], DataConfig(holdout_every=7)).points
    keep, record = carve(surface, raw.viewmats[cameras.train], cameras.Ks[cameras.train], cameras.width,
                         cameras.height, [coverage[i] for i in cameras.train])
    assert keep.all() and record.kept == len(surface)
