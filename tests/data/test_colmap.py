"""COLMAP scene loading: tiny reconstructions built with pycolmap in tmp_path."""

from __future__ import annotations

import re
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from cusgs_jax.config import DataConfig  # noqa: E402
from cusgs_jax.data.colmap import SceneData, SceneError  # noqa: E402
from cusgs_jax.data.loader import load_cameras, load_scene  # noqa: E402
from cusgs_jax.errors import ConfigError  # noqa: E402
from cusgs_jax.testing.scenes import axis_angle_rotation  # noqa: E402

W, H = 32, 24
PINHOLE = (30.0, 31.0, 16.0, 12.0)


def make_scene(root, *, n=3, width=W, height=H, cameras=None, text=False, model_dir="sparse/0",
               num_points=5, write_images=True, seed=0, images_dir="images", image_mode="RGB",
               nan_pose=False):
    """Write a tiny COLMAP scene under `root`.

    cameras: list of (model_name, params, width, height); image i uses camera i % len(cameras).
    Returns a dict with the ground truth (names by image id, R, t, images, points, colours).
    """
    rng = np.random.default_rng(seed)
    cameras = cameras or [("PINHOLE", PINHOLE, width, height)]
    rec = pycolmap.Reconstruction()
    for cid, (model, params, cw, ch) in enumerate(cameras, start=1):
        cam = pycolmap.Camera(camera_id=cid, model=model, width=cw, height=ch, params=list(params))
        rec.add_camera_with_trivial_rig(cam)

    truth = dict(names={}, R={}, t={}, camera={}, images={})
    keypoints = rng.uniform(0, min(width, height), (num_points, 2))
    for iid in range(1, n + 1):
        name = f"img_{n - iid:02d}.png"  # ids and names in opposite orders
        rot = axis_angle_rotation(rng.normal(scale=0.3, size=3))
        t = rng.normal(size=3) + np.array([0.0, 0.0, 4.0])
        if nan_pose and iid == 2:
            t[0] = np.nan
        cid = (iid - 1) % len(cameras) + 1
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=cid, image_id=iid)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(rot), t))
        truth["names"][iid] = name
        truth["R"][name], truth["t"][name], truth["camera"][name] = rot, t, cid
        cw, ch = cameras[cid - 1][2], cameras[cid - 1][3]
        if image_mode == "L":
            pixels = rng.integers(0, 256, (ch, cw), dtype=np.uint8)
        elif image_mode == "RGBA":
            pixels = rng.integers(0, 256, (ch, cw, 4), dtype=np.uint8)
        else:
            pixels = rng.integers(0, 256, (ch, cw, 3), dtype=np.uint8)
        truth["images"][name] = pixels
        if write_images:
            (root / images_dir).mkdir(parents=True, exist_ok=True)
            iio.imwrite(root / images_dir / name, pixels)

    xyz = rng.normal(size=(num_points, 3))
    colors = rng.integers(0, 256, (num_points, 3), dtype=np.uint8)
    for p in range(num_points):
        track = pycolmap.Track()
        for iid in range(1, n + 1):
            track.add_element(iid, p)
        rec.add_point3D(xyz[p], track, colors[p])
    truth["points"], truth["colors"] = xyz, colors

    out = root / model_dir
    out.mkdir(parents=True, exist_ok=True)
    if text:
        rec.write_text(str(out))
    else:
        rec.write(str(out))
    return truth


def _check_matches_truth(scene: SceneData, truth, *, downscale=1):
    names = sorted(truth["names"].values())
    assert scene.names == tuple(names)
    n = len(names)
    assert scene.images.shape == (n, scene.height, scene.width, 3)
    assert scene.images.dtype == np.uint8
    assert scene.viewmats.shape == (n, 4, 4) and scene.viewmats.dtype == np.float64
    assert scene.Ks.shape == (n, 3, 3) and scene.Ks.dtype == np.float32
    rng = np.random.default_rng(1)
    world = np.concatenate([rng.normal(size=(6, 3)), np.ones((6, 1))], -1)
    for i, name in enumerate(names):
        rot, t = truth["R"][name], truth["t"][name]
        np.testing.assert_allclose(scene.viewmats[i] @ world.T,
                                   np.concatenate([rot @ world[:, :3].T + t[:, None],
                                                   np.ones((1, 6))]), atol=1e-5)
        np.testing.assert_array_equal(scene.viewmats[i, 3], [0, 0, 0, 1])
    # Points: written in id order = sorted by id.
    np.testing.assert_allclose(scene.points, truth["points"], atol=1e-6)
    np.testing.assert_array_equal(scene.point_colors, truth["colors"])
    assert scene.points.dtype == np.float64 and scene.point_colors.dtype == np.uint8


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_load_model(tmp_path, text):
    truth = make_scene(tmp_path, n=3, text=text)
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    _check_matches_truth(scene, truth)
    assert (scene.width, scene.height) == (W, H)
    for i, name in enumerate(scene.names):
        np.testing.assert_array_equal(scene.images[i], truth["images"][name])
    fx, fy, cx, cy = PINHOLE
    np.testing.assert_allclose(scene.Ks, np.broadcast_to([[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                                                         (3, 3, 3)))
    # Extent by hand: camera centres C = -Rᵀt.
    centers = np.stack([-truth["R"][n].T @ truth["t"][n] for n in scene.names])
    np.testing.assert_allclose(scene.camera_centers, centers, atol=1e-5)
    expect = 1.1 * max(np.linalg.norm(c - centers.mean(0)) for c in centers)
    assert scene.extent == pytest.approx(expect, rel=1e-5)
    # 3 images, every 8th held out: test = [0].
    np.testing.assert_array_equal(scene.test_indices, [0])
    np.testing.assert_array_equal(scene.train_indices, [1, 2])
    assert scene.path == tmp_path


def test_model_without_rig_and_frame_files_in_sparse(tmp_path):
    """COLMAP 3.x layout: no rigs/frames files, model directly in sparse/."""
    truth = make_scene(tmp_path, model_dir="sparse")
    for f in ("rigs.bin", "frames.bin"):
        (tmp_path / "sparse" / f).unlink()
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    _check_matches_truth(scene, truth)


def test_holdout_split(tmp_path):
    make_scene(tmp_path, n=9, num_points=3)
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    np.testing.assert_array_equal(scene.test_indices, [0, 8])
    np.testing.assert_array_equal(scene.train_indices, np.arange(1, 8))
    assert scene.test_indices.dtype == np.int32 and scene.train_indices.dtype == np.int32
    scene = load_scene(tmp_path, DataConfig(format="colmap", holdout_every=3))
    np.testing.assert_array_equal(scene.test_indices, [0, 3, 6])
    scene = load_scene(tmp_path, DataConfig(format="colmap", holdout_every=0))
    assert scene.test_indices.size == 0
    np.testing.assert_array_equal(scene.train_indices, np.arange(9))
    with pytest.raises(SceneError, match="data.holdout_every"):
        load_scene(tmp_path, DataConfig(format="colmap", holdout_every=1))
    with pytest.raises(ConfigError, match="data.holdout_every"):  # refused by DataConfig itself
        load_scene(tmp_path, DataConfig(format="colmap", holdout_every=-1))


def test_simple_pinhole_and_per_image_cameras(tmp_path):
    cams = [("SIMPLE_PINHOLE", (28.0, 15.5, 12.5), W, H), ("PINHOLE", PINHOLE, W, H)]
    truth = make_scene(tmp_path, n=4, cameras=cams)
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    _check_matches_truth(scene, truth)
    for i, name in enumerate(scene.names):
        if truth["camera"][name] == 1:
            expect = [[28.0, 0, 15.5], [0, 28.0, 12.5], [0, 0, 1]]
        else:
            expect = [[30.0, 0, 16.0], [0, 31.0, 12.0], [0, 0, 1]]
        np.testing.assert_allclose(scene.Ks[i], expect)


def test_load_cameras_matches_load_scene_without_reading_images(tmp_path):
    cams = [("SIMPLE_PINHOLE", (28.0, 15.5, 12.5), W, H), ("PINHOLE", PINHOLE, W, H)]
    make_scene(tmp_path, n=9, cameras=cams)
    for downscale, every in ((1, 8), (2, 3), (1, 0)):
        scene = load_scene(tmp_path, DataConfig(format="colmap", downscale=downscale, holdout_every=every))
        cams = load_cameras(tmp_path, DataConfig(format="colmap", downscale=downscale, holdout_every=every))
        np.testing.assert_array_equal(cams.viewmats, scene.viewmats)
        np.testing.assert_array_equal(cams.Ks, scene.Ks)
        assert (cams.width, cams.height) == (scene.width, scene.height) and cams.Ks.dtype == np.float32
        np.testing.assert_array_equal(cams.train_indices, scene.train_indices)
    shutil.rmtree(tmp_path / "images")  # no image is read
    assert load_cameras(tmp_path, DataConfig(format="colmap")).viewmats.shape == (9, 4, 4)
    with pytest.raises(SceneError, match="data.holdout_every"):
        load_cameras(tmp_path, DataConfig(format="colmap", holdout_every=1))


@pytest.mark.parametrize("model,params", [  # distorted models that are not undistorted for the user
    ("FOV", (30.0, 31.0, 16.0, 12.0, 0.1)),
    ("THIN_PRISM_FISHEYE", (30.0, 31.0, 16.0, 12.0, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
])
def test_unsupported_camera_rejected(tmp_path, model, params):
    make_scene(tmp_path, cameras=[("PINHOLE", PINHOLE, W, H), (model, params, W, H)])
    with pytest.raises(SceneError, match=rf"camera 2 .*cameras\.bin.*{model}.*undistort") as e:
        load_scene(tmp_path, DataConfig(format="colmap"))
    assert "image_undistorter" in str(e.value)


def test_grey_and_rgba_images(tmp_path):
    truth = make_scene(tmp_path, image_mode="L")
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    for i, name in enumerate(scene.names):
        np.testing.assert_array_equal(scene.images[i], np.repeat(truth["images"][name][..., None],
                                                                 3, -1))
    shutil.rmtree(tmp_path / "images")
    truth = make_scene(tmp_path, image_mode="RGBA")
    scene = load_scene(tmp_path, DataConfig(format="colmap"))  # alpha composited onto the default black background
    for i, name in enumerate(scene.names):
        rgba = truth["images"][name].astype(np.float64)
        expect = np.round(rgba[..., :3] * (rgba[..., 3:] / 255.0)).astype(np.uint8)
        np.testing.assert_array_equal(scene.images[i], expect)


def test_downscale_from_images_folder(tmp_path):
    truth = make_scene(tmp_path)
    scene = load_scene(tmp_path, DataConfig(format="colmap", downscale=2))
    assert (scene.width, scene.height) == (W // 2, H // 2)
    assert scene.images.shape == (3, H // 2, W // 2, 3)
    fx, fy, cx, cy = PINHOLE
    np.testing.assert_allclose(scene.Ks[0], [[fx / 2, 0, cx / 2], [0, fy / 2, cy / 2], [0, 0, 1]])
    for i, name in enumerate(scene.names):  # 2×2 box average
        full = truth["images"][name].astype(np.float64)
        box = full.reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
        assert np.max(np.abs(scene.images[i] - box)) <= 0.5 + 1e-9
    _check_matches_truth(scene, truth)  # poses unchanged


def test_downscale_odd_size_rounds(tmp_path):
    """33×25 camera with downscale 2 → round(16.5)=17 × round(12.5)=13, anti-aliased."""
    make_scene(tmp_path, cameras=[("PINHOLE", (30.0, 30.0, 16.5, 12.5), 33, 25)])
    scene = load_scene(tmp_path, DataConfig(format="colmap", downscale=2))
    assert (scene.width, scene.height) == (17, 13)
    np.testing.assert_allclose(scene.Ks[0], [[15, 0, 8.25], [0, 15, 6.25], [0, 0, 1]])


def test_downscale_from_prescaled_folder(tmp_path):
    truth = make_scene(tmp_path)
    (tmp_path / "images_2").mkdir()
    small = {}
    rng = np.random.default_rng(5)
    for name in truth["names"].values():
        small[name] = rng.integers(0, 256, (H // 2, W // 2, 3), dtype=np.uint8)
        iio.imwrite(tmp_path / "images_2" / name, small[name])
    scene = load_scene(tmp_path, DataConfig(format="colmap", downscale=2))
    for i, name in enumerate(scene.names):
        np.testing.assert_array_equal(scene.images[i], small[name])
    fx, fy, cx, cy = PINHOLE
    np.testing.assert_allclose(scene.Ks[0], [[fx / 2, 0, cx / 2], [0, fy / 2, cy / 2], [0, 0, 1]])
    # Prescaled folder alone is enough (images/ not needed).
    shutil.rmtree(tmp_path / "images")
    assert load_scene(tmp_path, DataConfig(format="colmap", downscale=2)).images.shape == (3, H // 2, W // 2, 3)
    # images_2 with ±1 px (floor instead of round) is accepted.
    shutil.rmtree(tmp_path / "images_2")
    make_scene(tmp_path / "odd", cameras=[("PINHOLE", PINHOLE, 33, 25)], images_dir="images_2",
               write_images=False)
    (tmp_path / "odd" / "images_2").mkdir()
    for name in ("img_00.png", "img_01.png", "img_02.png"):
        iio.imwrite(tmp_path / "odd" / "images_2" / name, np.zeros((12, 16, 3), np.uint8))
    assert load_scene(tmp_path / "odd", DataConfig(format="colmap", downscale=2)).images.shape == (3, 12, 16, 3)


def test_prescaled_folder_with_wrong_factor(tmp_path):
    truth = make_scene(tmp_path)
    (tmp_path / "images_2").mkdir()
    for name in truth["names"].values():  # actually 4× smaller
        iio.imwrite(tmp_path / "images_2" / name, np.zeros((H // 4, W // 4, 3), np.uint8))
    with pytest.raises(SceneError, match=r"images_2.*img_00\.png is 8x6.*16x12.*data\.downscale=4"):
        load_scene(tmp_path, DataConfig(format="colmap", downscale=2))


def test_images_smaller_than_camera_suggest_downscale(tmp_path):
    truth = make_scene(tmp_path, write_images=False)
    (tmp_path / "images").mkdir()
    for name in truth["names"].values():
        iio.imwrite(tmp_path / "images" / name, np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(SceneError, match=r"img_00\.png is 16x12.*32x24.*images_2.*data\.downscale=2"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_image_size_disagrees_with_camera(tmp_path):
    make_scene(tmp_path)
    iio.imwrite(tmp_path / "images" / "img_01.png", np.zeros((20, 30, 3), np.uint8))
    with pytest.raises(SceneError, match=r"img_01\.png is 30x20 .*camera 1 \(32x24\).*32x24"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_cameras_of_different_sizes(tmp_path):
    make_scene(tmp_path, cameras=[("PINHOLE", PINHOLE, W, H), ("PINHOLE", PINHOLE, 40, 30)])
    with pytest.raises(SceneError, match=r"images\.bin.*32x24.*40x30"):
        load_scene(tmp_path, DataConfig(format="colmap"))


# ------------------------------------------------------------------------------------------
# Errors
# ------------------------------------------------------------------------------------------


def test_error_path_missing(tmp_path):
    with pytest.raises(SceneError, match=r"nope.*does not exist.*data\.path"):
        load_scene(tmp_path / "nope", DataConfig(format="colmap"))
    (tmp_path / "file").write_text("x")
    with pytest.raises(SceneError, match=r"file.*not a folder"):
        load_scene(tmp_path / "file", DataConfig(format="colmap"))


def test_error_images_folder_missing(tmp_path):
    make_scene(tmp_path, write_images=False)
    with pytest.raises(SceneError, match=re.escape(str(tmp_path / "images")) + ".*does not exist"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    with pytest.raises(SceneError, match=r"images_2.*data\.downscale=2"):
        load_scene(tmp_path, DataConfig(format="colmap", downscale=2))


def test_error_model_folder_missing(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(SceneError, match=r"no COLMAP model folder.*sparse"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    (tmp_path / "sparse" / "1").mkdir(parents=True)
    with pytest.raises(SceneError, match=r"no COLMAP model in .*sparse.*sub-folders 1"):
        load_scene(tmp_path, DataConfig(format="colmap"))


@pytest.mark.parametrize("part", ["cameras", "images", "points3D"])
def test_error_model_file_missing(tmp_path, part):
    make_scene(tmp_path)
    (tmp_path / "sparse" / "0" / f"{part}.bin").unlink()
    with pytest.raises(SceneError, match=rf"incomplete COLMAP model in .*sparse.0.*{part}\.bin/\.txt"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_error_model_unparsable(tmp_path):
    make_scene(tmp_path)
    model = tmp_path / "sparse" / "0"
    (model / "cameras.bin").write_bytes(b"\x01\x00")
    with pytest.raises(SceneError, match=r"cameras\.bin is truncated or corrupt"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    make_scene(tmp_path, write_images=False)
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[:40])  # count intact, records cut off
    with pytest.raises(SceneError, match=r"images\.bin is truncated or corrupt"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    (model / "images.bin").write_bytes(data[:8] + b"\xff" * (len(data) - 8))  # garbage records
    with pytest.raises(SceneError, match=r"sparse.0"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    shutil.rmtree(tmp_path / "sparse")
    make_scene(tmp_path, text=True, write_images=False)
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text("1 NOT_A_MODEL 32 24 1 2 3\n")
    with pytest.raises(SceneError, match=r"pycolmap could not read .*cameras\.txt"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_error_image_missing_on_disk(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images" / "img_01.png").unlink()
    with pytest.raises(SceneError, match=r"'img_01\.png'.*missing.*images.img_01\.png"):
        load_scene(tmp_path, DataConfig(format="colmap"))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio probing its legacy plugins
def test_error_image_corrupt(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images" / "img_02.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(SceneError, match=r"cannot decode image .*img_02\.png.*corrupt"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_a_downscale_that_leaves_no_pixel_is_refused_before_reading_images(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images" / "img_00.png").write_bytes(b"")  # not read: the check comes first
    with pytest.raises(SceneError, match=rf"data\.downscale=64 shrinks the images \({W}x{H} in .*cameras\..*\) to "
                                         r"\d+x0 pixels; use data\.downscale="):
        load_scene(tmp_path, DataConfig(format="colmap", downscale=64))


def test_error_no_points(tmp_path):
    make_scene(tmp_path, num_points=0)
    with pytest.raises(SceneError, match=r"no points.*points3D\.bin.*triangulat"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_error_non_finite_pose(tmp_path):
    make_scene(tmp_path, nan_pose=True)  # image id 2 = img_01.png
    with pytest.raises(SceneError, match=r"'img_01\.png'.*images\.bin.*non-finite"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_error_zero_images(tmp_path):
    make_scene(tmp_path, n=0, num_points=0)
    with pytest.raises(SceneError, match=r"images\.bin.*no registered images"):
        load_scene(tmp_path, DataConfig(format="colmap"))


def test_error_bad_downscale(tmp_path):
    make_scene(tmp_path)
    with pytest.raises(ConfigError, match=r"data\.downscale"):  # refused by DataConfig itself
        load_scene(tmp_path, DataConfig(format="colmap", downscale=0))
    with pytest.raises(SceneError, match=r"data\.downscale"):
        load_scene(tmp_path, DataConfig(format="colmap", downscale=1.5))


def test_multi_camera_rig(tmp_path):
    """pycolmap >= 3.12 rigs: an image's pose is sensor_from_rig ∘ rig_from_world."""
    rec = pycolmap.Reconstruction()
    cams = [pycolmap.Camera(camera_id=c, model="PINHOLE", width=W, height=H, params=list(PINHOLE))
            for c in (1, 2)]
    for cam in cams:
        rec.add_camera(cam)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(cams[0].sensor_id)
    r_s, t_s = axis_angle_rotation([0, 0.2, 0]), np.array([0.5, 0.0, 0.0])
    rig.add_sensor(cams[1].sensor_id, pycolmap.Rigid3d(pycolmap.Rotation3d(r_s), t_s))
    rec.add_rig(rig)
    r_w, t_w = axis_angle_rotation([0.1, 0, 0.3]), np.array([0.0, 1.0, 4.0])
    frame = pycolmap.Frame(frame_id=1, rig_id=1)
    frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(r_w), t_w)
    images = [pycolmap.Image(name=f"cam{c}.png", keypoints=np.array([[3.0, 4.0]]), camera_id=c,
                             image_id=c) for c in (1, 2)]
    for image in images:
        image.frame_id = 1
        frame.add_data_id(image.data_id)
    rec.add_frame(frame)
    for image in images:
        rec.add_image(image)
    rec.register_frame(1)
    track = pycolmap.Track()
    track.add_element(1, 0)
    track.add_element(2, 0)
    rec.add_point3D(np.array([0.1, 0.2, 0.3]), track, np.array([1, 2, 3], np.uint8))
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write(str(tmp_path / "sparse" / "0"))
    (tmp_path / "images").mkdir()
    for c in (1, 2):
        iio.imwrite(tmp_path / "images" / f"cam{c}.png", np.zeros((H, W, 3), np.uint8))
    scene = load_scene(tmp_path, DataConfig(format="colmap"))
    assert scene.names == ("cam1.png", "cam2.png")
    np.testing.assert_allclose(scene.viewmats[0, :3, :3], r_w, atol=1e-6)
    np.testing.assert_allclose(scene.viewmats[0, :3, 3], t_w, atol=1e-6)
    np.testing.assert_allclose(scene.viewmats[1, :3, :3], r_s @ r_w, atol=1e-6)
    np.testing.assert_allclose(scene.viewmats[1, :3, 3], r_s @ t_w + t_s, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Damaged binary models (exact structural walk) and duplicate image names
# ------------------------------------------------------------------------------------------


@pytest.fixture
def demo_copy(demo, tmp_path):
    """A private copy (images/ + sparse/) of the tiny demo scene, to damage."""
    for sub in ("images", "sparse"):
        shutil.copytree(demo / sub, tmp_path / sub)
    return tmp_path


def test_demo_binary_model_loads(demo_copy):
    """The intact pycolmap-written model passes the structural walk and loads."""
    scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0))
    assert scene.num_images == 4 and scene.points.shape[0] > 0


@pytest.mark.parametrize("part,record", [("cameras", "camera record 1 of 1"),
                                         ("images", "image record 4 of 4"),
                                         ("points3D", r"point record (\d+) of \1")])
@pytest.mark.parametrize("cut", [3, 8])
def test_error_binary_model_truncated_mid_record(demo_copy, part, record, cut):
    """Cutting a few bytes off the last record (cameras.bin minus 8 bytes used to load with
    cy = garbage) names the file, the broken record and the fix."""
    path = demo_copy / "sparse" / "0" / f"{part}.bin"
    path.write_bytes(path.read_bytes()[:-cut])
    with pytest.raises(SceneError, match=rf"{part}\.bin is truncated or corrupt: {record} "
                                         rf".*runs {cut} bytes past the end.*model_converter"):
        load_scene(demo_copy, DataConfig(format="colmap"))


@pytest.mark.parametrize("part", ["cameras", "images", "points3D"])
def test_error_binary_model_trailing_bytes(demo_copy, part):
    path = demo_copy / "sparse" / "0" / f"{part}.bin"
    size = path.stat().st_size
    path.write_bytes(path.read_bytes() + b"\0" * 5)
    with pytest.raises(SceneError, match=rf"{part}\.bin is truncated or corrupt: 5 trailing bytes"
                                         rf".*end at byte {size} of {size + 5}.*rerun SfM"):
        load_scene(demo_copy, DataConfig(format="colmap"))


def test_error_binary_camera_model_unknown(demo_copy):
    path = demo_copy / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    data[12:16] = (99).to_bytes(4, "little")  # count (8), camera_id (4), then model_id
    path.write_bytes(bytes(data))
    with pytest.raises(SceneError, match=r"cameras\.bin .*camera record 1 of 1 \(camera id 1.*"
                                         r"unknown camera model id 99"):
        load_scene(demo_copy, DataConfig(format="colmap"))


@pytest.mark.parametrize("part", ["cameras", "images", "points3D"])
def test_error_binary_model_implausible_count(demo_copy, part):
    path = demo_copy / "sparse" / "0" / f"{part}.bin"
    data = path.read_bytes()
    path.write_bytes((10**12).to_bytes(8, "little") + data[8:])
    with pytest.raises(SceneError, match=rf"{part}\.bin .*claims 1000000000000 .*can hold at most"):
        load_scene(demo_copy, DataConfig(format="colmap"))


def test_error_binary_track_length_implausible(demo_copy):
    """A corrupt track length in the first point stops the walk at that point."""
    path = demo_copy / "sparse" / "0" / "points3D.bin"
    data = bytearray(path.read_bytes())
    data[8 + 43:8 + 51] = (2**40).to_bytes(8, "little")  # point 1: id, xyz, rgb, error, then it
    path.write_bytes(bytes(data))
    with pytest.raises(SceneError, match=r"points3D\.bin .*point record 1 of \d+ \(byte offset 8, "
                                         r"point id \d+, track length 1099511627776\)"):
        load_scene(demo_copy, DataConfig(format="colmap"))


def _write_text_model(root, images):
    """A text COLMAP model in root/sparse/0 with one PINHOLE camera, ``images`` = [(id, name),
    ...] (all posed, no keypoints) and one point, plus black images under root/images."""
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"1 PINHOLE {W} {H} {' '.join(map(str, PINHOLE))}\n")
    lines = "".join(f"{iid} 1 0 0 0 {0.1 * iid} 0 4 1 {name}\n\n" for iid, name in images)
    (model / "images.txt").write_text(lines)
    (model / "points3D.txt").write_text("1 0.1 0.2 0.3 255 0 0 0.5\n")
    (root / "images").mkdir()
    for _, name in images:
        iio.imwrite(root / "images" / name, np.zeros((H, W, 3), np.uint8))


def test_error_duplicate_image_names(tmp_path):
    _write_text_model(tmp_path, [(1, "a.png"), (5, "b.png"), (7, "a.png")])
    with pytest.raises(SceneError, match=r"images\.txt has 2 registered images named 'a\.png' "
                                         r"\(image ids 1, 7\).*unique name.*image_deleter"):
        load_scene(tmp_path, DataConfig(format="colmap"))
    # Unique names load (the text model above is otherwise valid).
    shutil.rmtree(tmp_path / "sparse")
    shutil.rmtree(tmp_path / "images")
    _write_text_model(tmp_path, [(1, "a.png"), (5, "b.png"), (7, "c.png")])
    assert load_scene(tmp_path, DataConfig(format="colmap")).names == ("a.png", "b.png", "c.png")


def test_error_duplicate_image_names_binary(tmp_path):
    """The same model converted to binary by pycolmap is rejected too."""
    _write_text_model(tmp_path, [(1, "a.png"), (2, "a.png")])
    model = tmp_path / "sparse" / "0"
    pycolmap.Reconstruction(str(model)).write(str(model))
    for part in ("cameras", "images", "points3D"):
        (model / f"{part}.txt").unlink()
    with pytest.raises(SceneError, match=r"images\.bin has 2 registered images named 'a\.png'"):
        load_scene(tmp_path, DataConfig(format="colmap"))
