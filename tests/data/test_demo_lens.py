"""The demo room through a distorting lens (cusgs_jax.data.demo.lens), at a tiny size.

The strongest check is end to end: the lens images, undistorted by the COLMAP loader, must show
what a pinhole camera with the undistorted intrinsics sees from the same pose (the pinhole demo's
ray casting), so the lens ray casting, the COLMAP model and the undistortion agree with each other.
"""

from __future__ import annotations

import dataclasses
import filecmp
import json

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

pycolmap = pytest.importorskip("pycolmap")

from cusgs_jax.config import DataConfig, DemoConfig  # noqa: E402
from cusgs_jax.data.loader import load_scene  # noqa: E402
from cusgs_jax.data.demo import generate_demo_scene  # noqa: E402
from cusgs_jax.data.demo.lens import (LENSES, configured_demo, lens_camera, lens_demo_folder, lens_demo_path,  # noqa: E402
                                      render_lens_view, write_lens_demo)
from cusgs_jax.data.demo.render import build_scene, render_view  # noqa: E402

TINY = dict(num_views=3, width=64, height=48, num_points=800)
# Mean |difference| (0-255) of the undistorted lens image and the pinhole render, both blurred with
# sigma 1 px (bilinear resampling blurs one and not the other), 3 px borders left out. Measured: at
# most 2.2 when right, at least 4.7 with the reference moved by half a pixel.
_BLUR, _TOL = 1.0, 3.0


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    """The undistorted images and lens demos are cached in the test's own folder."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(cache))
    return cache


@pytest.fixture(scope="module")
def room():
    return build_scene()


def test_lens_cameras():
    assert lens_camera("pinhole", 160, 120) == ("PINHOLE", [128.0, 128.0, 80.0, 60.0])
    model, params = lens_camera("opencv", 160, 120)
    assert model == "OPENCV" and params[0] != params[1] and params[2:4] != [80.0, 60.0]
    assert params[4:] == [0.09, 0.02, 0.001, -0.0015]
    assert lens_camera("simple_radial", 160, 120) == ("SIMPLE_RADIAL", [128.0, 80.0, 60.0, 0.09])
    with pytest.raises(ValueError, match="unknown lens 'fisheye'"):
        lens_camera("fisheye", 160, 120)


def test_pinhole_lens_is_the_demo(tmp_path):
    """Through the pinhole lens the generator writes the demo scene itself."""
    demo = generate_demo_scene(tmp_path / "demo", **{k: v for k, v in TINY.items()})
    lens = write_lens_demo(tmp_path / "lens", *lens_camera("pinhole", 64, 48), **TINY)
    for v in range(TINY["num_views"]):
        name = f"view_{v:03d}"
        assert np.array_equal(iio.imread(demo / "images" / f"{name}.png"), iio.imread(lens / "images" / f"{name}.png"))
        assert np.array_equal(np.load(demo / "depth" / f"{name}.npy"), np.load(lens / "depth" / f"{name}.npy"))
    for part in ("cameras.bin", "images.bin", "points3D.bin"):
        assert filecmp.cmp(demo / "sparse" / "0" / part, lens / "sparse" / "0" / part, shallow=False), part


@pytest.mark.parametrize("lens", ["opencv", "simple_radial"])
def test_undistorted_lens_images_are_the_pinhole_renders(tmp_path, lens, room):
    root = write_lens_demo(tmp_path / lens, *lens_camera(lens, 64, 48), **TINY)
    raw = iio.imread(root / "images" / "view_000.png")
    scene = load_scene(root, DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    assert scene.width < 64 and scene.height < 48  # pincushion: cropped, no blank border
    for v in range(TINY["num_views"]):
        R, t = scene.viewmats[v][:3, :3], scene.viewmats[v][:3, 3]
        K = scene.Ks[v].astype(np.float64)
        errors = []
        for dx in (0.0, 0.5):  # the right intrinsics, and the principal point half a pixel off
            ref, *_ = render_view(room, R, t, scene.width, scene.height,
                                  (K[0, 0], K[1, 1], K[0, 2] + dx, K[1, 2] + dx))
            diff = gaussian_filter(ref.astype(float), (_BLUR, _BLUR, 0)) - gaussian_filter(
                scene.images[v].astype(float), (_BLUR, _BLUR, 0))
            errors.append(np.abs(diff[3:-3, 3:-3]).mean())
        assert errors[0] < _TOL < errors[1], (v, errors)
    # and the lens images themselves are not pinhole images of that size
    pin, *_ = render_view(room, scene.viewmats[0][:3, :3], scene.viewmats[0][:3, 3], 64, 48,
                          (51.2, 51.2, 32.0, 24.0))
    assert np.abs(pin.astype(float) - raw).mean() > 3.0


def test_keypoints_see_their_points(tmp_path, room):
    """Every keypoint of the lens model lies (through the lens) on its point: the lens's pixel-centre
    depth at the keypoint's pixel agrees with the point's depth wherever the keypoint is inside."""
    root = write_lens_demo(tmp_path / "s", *lens_camera("opencv", 64, 48), **TINY)
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    camera = next(iter(rec.cameras.values()))
    assert camera.model.name == "OPENCV"
    good = total = 0
    for image in rec.images.values():
        pose = image.cam_from_world()
        _, depth, _, _ = render_lens_view(room, pose.rotation.matrix(), pose.translation, camera)
        for p2 in image.points2D:
            if not p2.has_point3D():
                continue
            z = (pose * rec.points3D[p2.point3D_id].xyz)[2]
            u, v = p2.xy
            if 0 <= u < 64 and 0 <= v < 48:
                total += 1
                good += abs(depth[int(v), int(u)] - z) < 0.03 * z
    assert total > 100 and good / total > 0.9, (good, total)


def test_maps_line_up_with_the_loaded_images(tmp_path, room):
    """depth/ and object_ids/ are the ray casts of the undistorted camera the loader gives."""
    root = write_lens_demo(tmp_path / "s", *lens_camera("simple_radial", 64, 48), **TINY)
    scene = load_scene(root, DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    K = scene.Ks[1].astype(np.float64)
    _, depth, ids, _ = render_view(room, scene.viewmats[1][:3, :3], scene.viewmats[1][:3, 3], scene.width,
                                   scene.height, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), supersample=False)
    assert np.load(root / "object_ids" / "view_001.npy").shape == (scene.height, scene.width)
    np.testing.assert_allclose(np.load(root / "depth" / "view_001.npy"), depth, rtol=1e-4)
    assert np.mean(np.load(root / "object_ids" / "view_001.npy") == ids) > 0.99


def test_same_points_as_the_demo(tmp_path):
    demo = generate_demo_scene(tmp_path / "demo", **TINY)
    lens = write_lens_demo(tmp_path / "lens", *lens_camera("simple_radial", 64, 48), **TINY)
    a, b = (pycolmap.Reconstruction(str(s / "sparse" / "0")) for s in (demo, lens))
    assert sorted(a.points3D) == sorted(b.points3D) and len(a.points3D) > 100
    for pid, p in a.points3D.items():
        q = b.points3D[pid]
        assert np.array_equal(p.xyz, q.xyz) and np.array_equal(p.color, q.color)
        assert [e.image_id for e in p.track.elements] == [e.image_id for e in q.track.elements]
    info = json.loads((lens / "scene.json").read_text())
    assert info["camera_model"] == "SIMPLE_RADIAL" and info["camera_params"][3] == 0.09


def test_bad_camera(tmp_path):
    with pytest.raises(ValueError, match="OPENCV takes the params fx, fy, cx, cy, k1, k2, p1, p2"):
        write_lens_demo(tmp_path / "s", "OPENCV", [50.0, 32.0, 24.0, 0.1], **TINY)
    (tmp_path / "t" / "images").mkdir(parents=True)
    with pytest.raises(FileExistsError):
        write_lens_demo(tmp_path / "t", *lens_camera("opencv", 64, 48), **TINY)


def test_lens_demo_path_caches(cache_dir):
    small = dict(num_views=2, width=32, height=24)
    assert lens_demo_folder(lens="pinhole", **small).name.startswith("demo3-")  # the demo's folder
    path = lens_demo_path(lens="opencv", **small)
    assert path == lens_demo_folder(lens="opencv", **small) and path.parent == cache_dir
    assert json.loads((path / "scene.json").read_text())["lens"] == "opencv"
    stamp = (path / "scene.json").stat().st_mtime_ns
    assert lens_demo_path(lens="opencv", **small) == path and (path / "scene.json").stat().st_mtime_ns == stamp
    # a run's data.demo names the same folder, found (not generated) or generated
    demo = DemoConfig(views=2, width=32, height=24, lens="opencv")
    assert configured_demo(demo) == path == configured_demo(demo, generate=True)
    assert (path / "scene.json").stat().st_mtime_ns == stamp
    assert not configured_demo(dataclasses.replace(demo, lens="simple_radial")).exists()  # not generated
    assert set(LENSES) == {"pinhole", "opencv", "simple_radial"}


def test_masked_maps_line_up_with_the_images_undistorted_with_a_mask(tmp_path, room):
    """masked/depth/ and masked/object_ids/ are the ray casts of the source-frame camera that
    data.undistort=mask gives, and the semantic features of a masked scene are extracted from them."""
    from cusgs_jax.extract import extract_scene

    root = write_lens_demo(tmp_path / "s", *lens_camera("simple_radial", 64, 48), **TINY)
    scene = load_scene(root, DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    assert (scene.width, scene.height) == (64, 48) and scene.valid is not None
    K = scene.Ks[1].astype(np.float64)
    _, depth, ids, _ = render_view(room, scene.viewmats[1][:3, :3], scene.viewmats[1][:3, 3], 64, 48,
                                   (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), supersample=False)
    np.testing.assert_allclose(np.load(root / "masked" / "depth" / "view_001.npy"), depth, rtol=1e-4)
    assert np.mean(np.load(root / "masked" / "object_ids" / "view_001.npy") == ids) > 0.99
    assert json.loads((root / "scene.json").read_text())["masked_maps_camera"]["width"] == 64
    extract_scene(scene, "semantic", progress=False)  # the masked scene loaded above
    from cusgs_jax.data.features import load_features

    fs = load_features(root, "semantic", scene.names)
    assert fs.meta["undistort"] == "mask" and fs.maps.shape[1:3] == (48, 64)
    # one vector per object: the pixels of one object id share a vector, different ids differ
    masked_ids = np.load(root / "masked" / "object_ids" / "view_001.npy")
    vectors = {int(i): fs.maps[1][masked_ids == i] for i in np.unique(masked_ids) if i}
    assert all(np.allclose(v, v[0]) for v in vectors.values()) and len(vectors) > 1
