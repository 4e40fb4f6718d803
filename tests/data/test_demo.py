"""The built-in demo scene (cusgs_jax.data.demo) on a tiny version: 6 views at 40x30."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pycolmap
import pytest

from cusgs_jax.data import demo
from cusgs_jax.data.demo import FORMAT_VERSION, demo_scene_path, generate_demo_scene
from cusgs_jax.data.demo.render import TABLE_CENTRE

TINY = dict(num_views=6, width=40, height=30)
# 6 views spaced 60 degrees apart see little of the room twice at 40x30, so sample more
# surface points than the final model needs (only points seen in >= 2 views are kept).
TINY_POINTS = 1500


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "scene"
    return generate_demo_scene(out, seed=0, num_points=TINY_POINTS, **TINY)


def _read(scene):
    return pycolmap.Reconstruction(str(scene / "sparse" / "0"))


def _points(rec):
    ids = sorted(rec.point3D_ids())
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    rgb = np.array([rec.points3D[i].color for i in ids])
    tracks = [sorted((e.image_id, e.point2D_idx) for e in rec.points3D[i].track.elements)
              for i in ids]
    return xyz, rgb, tracks


def _poses(rec):
    return {rec.image(i).name: rec.image(i).cam_from_world().matrix() for i in rec.reg_image_ids()}


def test_layout(tiny):
    names = [f"view_{i:03d}.png" for i in range(6)]
    assert sorted(p.name for p in (tiny / "images").iterdir()) == names
    for part in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (tiny / "sparse" / "0" / part).is_file()
    for i in range(6):
        d = np.load(tiny / "depth" / f"view_{i:03d}.npy")
        o = np.load(tiny / "object_ids" / f"view_{i:03d}.npy")
        assert d.shape == o.shape == (30, 40) and d.dtype == np.float32
        assert o.dtype in (np.uint8, np.uint16)
    info = json.loads((tiny / "scene.json").read_text())
    assert (info["seed"], info["num_views"], info["width"], info["height"]) == (0, 6, 40, 30)


def test_deterministic(tiny, tmp_path):
    again = generate_demo_scene(tmp_path / "again", seed=0, num_points=TINY_POINTS, **TINY)
    for i in range(6):
        name = f"view_{i:03d}"
        assert (tiny / "images" / f"{name}.png").read_bytes() == \
            (again / "images" / f"{name}.png").read_bytes()
        for sub in ("depth", "object_ids"):
            np.testing.assert_array_equal(np.load(tiny / sub / f"{name}.npy"),
                                          np.load(again / sub / f"{name}.npy"))
    a, b = _read(tiny), _read(again)
    xa, ca, ta = _points(a)
    xb, cb, tb = _points(b)
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(ca, cb)
    assert ta == tb
    pa, pb = _poses(a), _poses(b)
    assert all(np.array_equal(pa[k], pb[k]) for k in pa)

    other = _read(generate_demo_scene(tmp_path / "other", seed=1, num_points=TINY_POINTS, **TINY))
    po = _poses(other)
    assert all(not np.allclose(pa[k], po[k], atol=1e-3) for k in pa)


def test_colmap_model(tiny):
    rec = _read(tiny)
    assert rec.num_reg_images() == rec.num_images() == 6
    assert sorted(rec.image(i).name for i in rec.reg_image_ids()) == \
        [f"view_{i:03d}.png" for i in range(6)]
    assert rec.num_cameras() == 1
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (40, 30)
    np.testing.assert_allclose(cam.params, [32.0, 32.0, 20.0, 15.0])
    assert rec.num_points3D() > 100
    for pid, pt in rec.points3D.items():
        assert pt.track.length() >= 2
        for e in pt.track.elements:
            assert rec.image(e.image_id).points2D[e.point2D_idx].point3D_id == pid


def test_reprojection_and_depth(tiny):
    rec = _read(tiny)
    cam = next(iter(rec.cameras.values()))
    fx, fy, cx, cy = cam.params
    depth = {n: np.load(tiny / "depth" / n.replace(".png", ".npy")) for n in _poses(rec)}
    objs = {n: np.load(tiny / "object_ids" / n.replace(".png", ".npy")) for n in _poses(rec)}
    n_obs = 0
    for pid, pt in rec.points3D.items():
        for e in pt.track.elements:
            img = rec.image(e.image_id)
            xc = img.cam_from_world().matrix() @ np.append(pt.xyz, 1.0)
            assert xc[2] > 0
            uv = np.array([fx * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy])
            obs = img.points2D[e.point2D_idx].xy
            assert np.linalg.norm(uv - obs) < 0.5
            col, row = int(np.floor(obs[0])), int(np.floor(obs[1]))
            assert 0 <= col < 40 and 0 <= row < 30
            d = float(depth[img.name][row, col])
            assert abs(d - xc[2]) <= 1e-2 * xc[2] + 1e-6, (pid, img.name, d, xc[2])
            assert objs[img.name][row, col] > 0
            n_obs += 1
    assert n_obs >= 2 * rec.num_points3D()


def test_objects(tiny):
    objects = json.loads((tiny / "objects.json").read_text())
    ids = [o["id"] for o in objects]
    assert len(set(ids)) == len(ids) and 0 not in ids
    assert len({o["texture"] for o in objects}) == len(objects)  # a different photo each
    names = {o["name"] for o in objects}
    assert {"floor", "ceiling", "table_top", "table_legs", "chair", "cabinet"} <= names
    seen = set()
    for i in range(6):
        o = np.load(tiny / "object_ids" / f"view_{i:03d}.npy")
        d = np.load(tiny / "depth" / f"view_{i:03d}.npy")
        assert np.all(d[o > 0] > 0)
        assert np.all(o[d > 0] > 0)
        seen |= set(np.unique(o).tolist())
    seen.discard(0)
    assert len(seen) >= 5
    assert seen <= set(ids)


def test_images_textured(tiny):
    for i in range(6):
        img = iio.imread(tiny / "images" / f"view_{i:03d}.png")
        assert img.shape == (30, 40, 3) and img.dtype == np.uint8
        assert img.std() > 10


def test_cameras_look_at_table(tiny):
    rec = _read(tiny)
    cam = next(iter(rec.cameras.values()))
    fx, fy, cx, cy = cam.params
    for m in _poses(rec).values():
        xc = m @ np.append(TABLE_CENTRE, 1.0)  # OpenCV: the table is in front, near centre
        assert xc[2] > 1.0
        assert abs(fx * xc[0] / xc[2] + cx - 20) < 10 and abs(fy * xc[1] / xc[2] + cy - 15) < 8
        centre = -m[:, :3].T @ m[:, 3]
        assert np.all(np.abs(centre[:2]) < 3) and 0 < centre[2] < 3  # inside the room


def test_demo_scene_path_caches(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    cache.mkdir()
    # Leftovers of an interrupted generation must not get in the way.
    stale = cache / f".demo{FORMAT_VERSION}-s0-v6-40x30.tmp-interrupted"
    (stale / "images").mkdir(parents=True)
    (stale / "images" / "view_000.png").write_bytes(b"partial")
    path = demo_scene_path(cache, seed=0, **TINY)
    assert path == cache / f"demo{FORMAT_VERSION}-s0-v6-40x30"
    assert _read(path).num_images() == 6
    assert not any(p.name.startswith(f".demo{FORMAT_VERSION}-s0-v6-40x30.tmp-") and p != stale
                   for p in cache.iterdir())  # our own temporary folder is gone
    mtime = (path / "scene.json").stat().st_mtime_ns

    def boom(*args, **kwargs):
        raise AssertionError("regenerated a cached scene")

    monkeypatch.setattr(demo, "generate_demo_scene", boom)
    assert demo_scene_path(cache, seed=0, **TINY) == path
    assert (path / "scene.json").stat().st_mtime_ns == mtime
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(cache))
    assert demo_scene_path(seed=0, **TINY) == path


def test_demo_scene_path_replaces_incomplete_folder(tmp_path):
    cache = tmp_path / "cache"
    broken = cache / f"demo{FORMAT_VERSION}-s3-v6-40x30"
    (broken / "images").mkdir(parents=True)  # no scene.json: not a finished scene
    path = demo_scene_path(cache, seed=3, **TINY)
    assert path == broken and (path / "scene.json").is_file()
    assert _read(path).num_images() == 6
