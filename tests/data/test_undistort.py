"""Distorted COLMAP cameras: undistorted to PINHOLE with COLMAP's undistorter into the cache.

Tiny synthetic scenes (:mod:`cusgs_jax.testing.distorted_scenes`: 8 images of 64×48 rendered
through their distorted cameras, one marker per 3D point) are loaded, and each marker must sit on
the pinhole projection ``K · viewmat · X`` of its point.
"""

from __future__ import annotations

import logging
import os
import shutil
import stat

import imageio.v3 as iio
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from cusgs_jax.data import undistort  # noqa: E402
from cusgs_jax.config import DataConfig  # noqa: E402
from cusgs_jax.data.colmap import SceneError  # noqa: E402
from cusgs_jax.data.loader import load_cameras, load_scene  # noqa: E402
from cusgs_jax.errors import ConfigError  # noqa: E402
from cusgs_jax.data.images import downscale_image, scaled_size  # noqa: E402
from cusgs_jax.testing.distorted_scenes import (BACKGROUND, CAMERAS, H, N_VIEWS, W,  # noqa: E402
                                                distorted_colmap_scene, marker_errors)

@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    """Every test caches into its own folder, never ~/.cache."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(cache))
    return cache


@pytest.fixture
def calls(monkeypatch):
    """Counts the calls of pycolmap.undistort_images (the list of their output folders)."""
    seen = []
    real = pycolmap.undistort_images

    def counting(*args, **kwargs):
        seen.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "undistort_images", counting)
    return seen


MIXED = [("OPENCV", CAMERAS["OPENCV"]), ("OPENCV", (50.0, 51.0, 31.8, 24.2, -0.2, 0.05, 0.0, 0.0)),
         ("PINHOLE", (50.0, 50.0, 32.0, 24.0))]


@pytest.mark.parametrize("cameras,ext", [([(m, p)], ".png") for m, p in CAMERAS.items()]
                         + [(MIXED, ".png"), (MIXED, ".jpg")],
                         ids=list(CAMERAS) + ["mixed_sizes", "mixed_sizes_jpeg"])
def test_distorted_scene_loads_as_pinhole(tmp_path, cameras, ext, calls):
    distorted_colmap_scene(tmp_path / "s", cameras, subfolder=len(cameras) > 1, ext=ext)
    scene = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    assert len(calls) == 1 and scene.images.shape == (N_VIEWS, scene.height, scene.width, 3)
    # Pinhole K of COLMAP's undistorted camera (centre-cropped to the common size when mixed).
    full = {cid: pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                           pycolmap.Camera(camera_id=cid, model=m, width=W, height=H,
                                                           params=list(p)))
            for cid, (m, p) in enumerate(cameras, start=1)}
    assert scene.width == min(c.width for c in full.values())
    assert scene.height == min(c.height for c in full.values())
    for name, K in zip(scene.names, scene.Ks):
        c = full[int(name[-6:-4]) % len(cameras) + 1]  # image i (v{i:02d}.png) has camera i % n
        x0, y0 = (c.width - scene.width) // 2, (c.height - scene.height) // 2
        np.testing.assert_allclose(K, [[c.focal_length_x, 0, c.principal_point_x - x0],
                                       [0, c.focal_length_y, c.principal_point_y - y0], [0, 0, 1]],
                                   rtol=1e-6)
    if len(cameras) > 1:  # a real crop happened
        assert len({(c.width, c.height) for c in full.values()}) > 1
    errors = marker_errors(scene)
    assert len(errors) >= 4 * N_VIEWS, "too few markers inside the undistorted images"
    assert max(errors) < 0.25, f"marker off its pinhole projection by {max(errors):.2f} px"


@pytest.mark.parametrize("model", list(CAMERAS))
def test_no_black_border(tmp_path, model):
    """Crop, not mask: a uniformly bright source gives uniformly bright undistorted images."""
    distorted_colmap_scene(tmp_path / "s", [(model, CAMERAS[model])], uniform=True)
    images = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop")).images
    images = images.astype(int)
    borders = np.concatenate([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], 1)
    assert borders.min() >= BACKGROUND - 1, f"dark border pixel {borders.min()}"
    assert np.abs(images - BACKGROUND).max() <= 1


def test_cache_reused_and_invalidated(tmp_path, cache_dir, calls, caplog):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])])
    with caplog.at_level(logging.INFO, logger="cusgs_jax"):
        first = load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
        assert len(calls) == 1
        line = f"undistorted {N_VIEWS} images OPENCV → PINHOLE {first.width}×{first.height}, cached in"
        assert line in caplog.text
        folders = list((cache_dir / "undistorted").iterdir())
        assert len(folders) == 1 and folders[0].name.startswith("s-")
        assert sorted(p.name for p in folders[0].iterdir()) == ["images", "undistort.json"]
        caplog.clear()
        second = load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
        assert len(calls) == 1 and "using cached undistorted images" in caplog.text
    np.testing.assert_array_equal(first.images, second.images)
    np.testing.assert_array_equal(first.Ks, second.Ks)
    # A changed image (new content, new mtime) makes a new cache entry.
    path = tmp_path / "s" / "images" / "v03.png"
    iio.imwrite(path, np.full((H, W, 3), 7, np.uint8))
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))
    third = load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    assert len(calls) == 2 and len(list((cache_dir / "undistorted").iterdir())) == 2
    assert third.images[3].max() <= 8 and np.array_equal(third.images[2], first.images[2])
    assert not list((cache_dir / "undistorted").glob(".*tmp-*"))  # temporary folders renamed


def test_lost_race_uses_the_winners_copy(tmp_path, cache_dir, monkeypatch):
    """Another job renames its complete copy into place first: ours is dropped, theirs used."""
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])])
    real = undistort._undistort_into

    def racing(tmp, *args, **kwargs):
        real(tmp, *args, **kwargs)
        final = tmp.parent / tmp.name[1:].split(".tmp-")[0]  # tmp is .<final name>.tmp-XXXX
        shutil.copytree(tmp, final)  # the other job got there first

    monkeypatch.setattr(undistort, "_undistort_into", racing)
    scene = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    assert [p.name.startswith("s-") for p in (cache_dir / "undistorted").iterdir()] == [True]
    assert max(marker_errors(scene)) < 0.25


def _snapshot(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns)
                  for p in folder.rglob("*"))


def test_read_only_scene(tmp_path, cache_dir):
    scene_dir = tmp_path / "s"
    distorted_colmap_scene(scene_dir, [("RADIAL", CAMERAS["RADIAL"])])
    before = _snapshot(scene_dir)
    modes = {p: p.stat().st_mode for p in [scene_dir, *scene_dir.rglob("*")]}
    for p in modes:
        p.chmod(stat.S_IMODE(modes[p]) & ~0o222)
    try:
        scene = load_scene(scene_dir, DataConfig(format="colmap", undistort="crop"))
    finally:
        for p, mode in modes.items():
            p.chmod(stat.S_IMODE(mode))
    assert scene.path == scene_dir and scene.num_images == N_VIEWS
    assert _snapshot(scene_dir) == before  # nothing written into the scene folder
    assert len(list((cache_dir / "undistorted").iterdir())) == 1


@pytest.mark.parametrize("model,params", [
    ("FOV", (50, 50, 32, 24, 0.1)),
    ("THIN_PRISM_FISHEYE", (50, 50, 32, 24, 0, 0, 0, 0, 0, 0, 0, 0)),
    ("SIMPLE_RADIAL_FISHEYE", (50, 32, 24, 0.01)),
])
def test_unsupported_model(tmp_path, model, params, calls):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"]), (model, params)], uniform=True)
    with pytest.raises(SceneError, match=rf"camera 2 in .*cameras\.bin uses the {model} camera "
                                         r"model.*colmap image_undistorter"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    with pytest.raises(SceneError, match=model):
        load_cameras(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    assert not calls


@pytest.mark.parametrize("downscale", [1, 2])
def test_load_cameras_agrees_with_load_scene(tmp_path, calls, downscale):
    distorted_colmap_scene(tmp_path / "s", MIXED)
    data = DataConfig(format="colmap", downscale=downscale, undistort="crop")
    cams = load_cameras(tmp_path / "s", data)
    assert not calls  # no image is undistorted (or read) for the cameras
    scene = load_scene(tmp_path / "s", data)
    assert (cams.width, cams.height) == (scene.width, scene.height)
    np.testing.assert_array_equal(cams.Ks, scene.Ks)
    np.testing.assert_array_equal(cams.viewmats, scene.viewmats)
    np.testing.assert_array_equal(cams.train_indices, scene.train_indices)


def test_downscale_uses_undistorted_full_resolution(tmp_path):
    """images_2/ of a distorted scene holds distorted pixels: ignored; the undistorted images/
    are downscaled with the loader's anti-aliased resize and K is halved."""
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])])
    shutil.copytree(tmp_path / "s" / "images", tmp_path / "s" / "images_2")
    for p in (tmp_path / "s" / "images_2").iterdir():
        iio.imwrite(p, np.zeros((H // 2, W // 2, 3), np.uint8))  # would be black if used
    full = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    half = load_scene(tmp_path / "s", DataConfig(format="colmap", downscale=2, holdout_every=0, undistort="crop"))
    out_hw = (scaled_size(full.height, 2), scaled_size(full.width, 2))
    assert (half.height, half.width) == out_hw
    for a, b in zip(full.images, half.images):
        np.testing.assert_array_equal(downscale_image(a, 2, out_hw), b)
    np.testing.assert_allclose(half.Ks[:, :2], full.Ks[:, :2] / 2, rtol=1e-6)


def test_zero_distortion_is_a_pinhole(tmp_path, calls):
    distorted_colmap_scene(tmp_path / "s", [("SIMPLE_RADIAL", (50.0, 32.0, 24.0, 0.0))])
    scene = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"))
    assert not calls and (scene.width, scene.height) == (W, H)
    np.testing.assert_allclose(scene.Ks[0], [[50, 0, 32], [0, 50, 24], [0, 0, 1]])
    assert max(marker_errors(scene)) < 0.25


def test_invalid_distorted_camera(tmp_path, calls):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", (50.0, 52.0, 32.0, 24.0, np.nan, 0.0, 0.0, 0.0))],
               uniform=True)
    with pytest.raises(SceneError, match=r"camera 1 in .*cameras\.bin has invalid parameters \(OPENCV"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    assert not calls


def test_missing_and_corrupt_images(tmp_path):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])], uniform=True)
    (tmp_path / "s" / "images" / "v02.png").unlink()
    with pytest.raises(SceneError, match=r"'v02\.png' .*missing"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    (tmp_path / "s" / "images" / "v02.png").write_bytes(b"not an image")
    with pytest.raises(SceneError, match=r"undistorter could not read image .*v02\.png"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))
    shutil.rmtree(tmp_path / "s" / "images")
    with pytest.raises(SceneError, match=r"images does not exist.*distorted"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))


def test_unwritable_cache(tmp_path, monkeypatch):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])], uniform=True)
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "file"))  # a file, not a folder
    with pytest.raises(SceneError, match=r"cannot write the undistorted images.*CUSGS_CACHE_DIR"):
        load_scene(tmp_path / "s", DataConfig(format="colmap", undistort="crop"))


def _rgba(seed):
    """[H, W, 4] uint8: a smooth colour ramp with a transparent disc and a half-transparent band."""
    ii, jj = np.mgrid[0:H, 0:W]
    rng = np.random.default_rng(seed)
    rgb = np.stack([40 + 3 * jj, 30 + 4 * ii, np.full((H, W), rng.integers(50, 200))], -1)
    alpha = np.full((H, W), 255)
    alpha[(ii - 20) ** 2 + (jj - 30) ** 2 < 90] = 0
    alpha[:, 45:52] = 128
    return np.concatenate([rgb, alpha[..., None]], -1).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("background", [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0)])
def test_alpha_kept_and_composited(tmp_path, background, caplog):
    """An RGBA image of a distorted scene keeps its alpha: loaded, it equals the image composited
    onto the background first and then undistorted by COLMAP (to 8-bit rounding)."""
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])], uniform=True)
    rgba = _rgba(1)
    iio.imwrite(tmp_path / "s" / "images" / "v01.png", rgba)
    with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
        scene = load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="crop"),
                           background=background)
    assert "drops it" not in caplog.text and "1 of 8 images" in caplog.text  # the loader's own warning
    cam = pycolmap.Camera(camera_id=1, model="OPENCV", width=W, height=H, params=list(CAMERAS["OPENCV"]))
    a = rgba[..., 3:] / 255.0
    composited = np.round(rgba[..., :3] * a + 255.0 * np.asarray(background) * (1 - a)).astype(np.uint8)
    ref, ref_cam = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(),
                                            pycolmap.Bitmap.from_array(composited), cam)
    ref = np.asarray(ref.to_array()).astype(int)
    got = scene.images[scene.names.index("v01.png")].astype(int)
    assert got.shape == ref.shape == (scene.height, scene.width, 3)
    assert np.abs(got - ref).max() <= 2
    # the transparent disc shows the background (its centre, 20 rows down and 30 across in the source)
    u, v = cam.cam_from_img(np.array([[30.5, 20.5]]))[0]
    j, i = int(ref_cam.focal_length_x * u + ref_cam.principal_point_x), int(ref_cam.focal_length_y * v + ref_cam.principal_point_y)
    assert np.array_equal(got[i, j], np.round(255 * np.asarray(background)))
    cached = next((tmp_path / "cache" / "undistorted").iterdir()) / "images"
    assert iio.imread(cached / "v01.png").shape[-1] == 4 and iio.imread(cached / "v00.png").shape[-1] == 3


def test_cache_key_changes_with_camera(tmp_path):
    """The key covers the camera parameters and the options, not only the image files."""
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])], uniform=True)
    views = [(f"v{i:02d}.png", 1) for i in range(N_VIEWS)]
    sources = [tmp_path / "s" / "images" / n for n, _ in views]
    cam = pycolmap.Camera(camera_id=1, model="OPENCV", width=W, height=H, params=list(CAMERAS["OPENCV"]))
    other = pycolmap.Camera(camera_id=1, model="OPENCV", width=W, height=H,
                            params=list(CAMERAS["OPENCV"][:4]) + [-0.12000001, 0.02, 0.001, -0.002])
    opts = pycolmap.UndistortCameraOptions()
    key = undistort._cache_key(views, sources, {1: cam}, opts, "v")
    assert key == undistort._cache_key(views, sources, {1: cam}, opts, "v")
    assert key != undistort._cache_key(views, sources, {1: other}, opts, "v")
    opts2 = pycolmap.UndistortCameraOptions()
    opts2.blank_pixels = 1.0
    assert key != undistort._cache_key(views, sources, {1: cam}, opts2, "v")


@pytest.mark.parametrize("model", list(CAMERAS))
def test_mask_mode_keeps_the_frame(tmp_path, model):
    """data.undistort=mask: the source size and intrinsics without distortion; the valid-pixel mask
    is exactly the bright part of a uniformly bright source, and the markers still sit on their
    pinhole projections."""
    distorted_colmap_scene(tmp_path / "u", [(model, CAMERAS[model])], uniform=True)
    scene = load_scene(tmp_path / "u", DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    source = pycolmap.Camera(model=model, width=W, height=H, params=list(CAMERAS[model]))
    assert (scene.width, scene.height) == (W, H)
    np.testing.assert_allclose(scene.Ks[0], [[source.focal_length_x, 0, source.principal_point_x],
                                             [0, source.focal_length_y, source.principal_point_y], [0, 0, 1]])
    assert scene.valid.shape == (N_VIEWS, H, W) and scene.valid.dtype == bool
    images = scene.images.astype(int)
    assert np.abs(images[scene.valid] - BACKGROUND).max() <= 1  # valid: image content only
    assert np.all(images[~scene.valid] < BACKGROUND // 2)  # invalid: COLMAP's black
    # Analytic check: a pixel whose source location lies > 1.5 px inside the frame is valid, one
    # > 1.5 px outside is not (COLMAP's bilinear footprint decides the pixels in between).
    pinhole = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[
        source.focal_length_x, source.focal_length_y, source.principal_point_x, source.principal_point_y])
    ys, xs = np.mgrid[0:H, 0:W]
    centres = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], -1).astype(np.float64)
    rays = pinhole.cam_from_img(centres)
    src = source.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], -1)).reshape(H, W, 2)
    inside = np.minimum(np.minimum(src[..., 0], W - src[..., 0]), np.minimum(src[..., 1], H - src[..., 1]))
    assert np.all(scene.valid[0][inside > 1.5]) and not np.any(scene.valid[0][inside < -1.5])
    if model == "SIMPLE_RADIAL":  # pincushion: the corners of the pinhole frame lie outside the source
        assert 0.02 < 1 - scene.valid.mean() < 0.3
    distorted_colmap_scene(tmp_path / "m", [(model, CAMERAS[model])])
    marked = load_scene(tmp_path / "m", DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    errors = marker_errors(marked)
    assert len(errors) >= 4 * N_VIEWS and max(errors) < 0.25, max(errors)
    # load_cameras gives the same cameras without undistorting
    cams = load_cameras(tmp_path / "m", DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    assert (cams.width, cams.height) == (W, H) and np.allclose(cams.Ks, marked.Ks)
    # crop mode has no mask and its own cache folder
    assert load_scene(tmp_path / "m", DataConfig(format="colmap", holdout_every=0, undistort="crop")).valid is None


def test_mask_mode_downscale_is_conservative(tmp_path):
    distorted_colmap_scene(tmp_path / "u", [("SIMPLE_RADIAL", CAMERAS["SIMPLE_RADIAL"])], uniform=True)
    full = load_scene(tmp_path / "u", DataConfig(format="colmap", holdout_every=0, undistort="mask"))
    half = load_scene(tmp_path / "u", DataConfig(format="colmap", holdout_every=0, undistort="mask", downscale=2))
    assert half.valid.shape == (N_VIEWS, scaled_size(H, 2), scaled_size(W, 2))
    # a downscaled pixel is valid only when no black pixel was mixed into it
    assert np.abs(half.images.astype(int)[half.valid] - BACKGROUND).max() <= 1
    blocks = full.valid.reshape(N_VIEWS, H // 2, 2, W // 2, 2).all(axis=(2, 4))
    assert not np.any(half.valid & ~blocks)  # never valid where a full-size pixel was not
    assert half.valid.mean() > 0.8 * blocks.mean()  # and not needlessly small


def test_bad_undistort_mode(tmp_path):
    distorted_colmap_scene(tmp_path / "s", [("OPENCV", CAMERAS["OPENCV"])])
    with pytest.raises(ConfigError, match=r"data.undistort.*'blur'.*crop.*mask.*lens"):  # refused before any reading
        load_scene(tmp_path / "s", DataConfig(format="colmap", holdout_every=0, undistort="blur"))
