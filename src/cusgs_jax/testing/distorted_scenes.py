"""Tiny COLMAP scenes with distorted cameras whose images show where every 3D point must land.

8 images of 64×48 (:data:`W`, :data:`H`, :data:`N_VIEWS`), written with pycolmap. Each image is
rendered through its distorted camera as a function of the viewing ray: a bright background with a
Gaussian marker (σ = 1.2 undistorted pixels, one colour channel per marker) around the ray of every
3D point of :data:`POINTS`, so in a correctly undistorted image each marker is centred on the pinhole
projection ``K · viewmat · X`` of its point (:func:`marker_errors`). Used by the undistortion tests of
the COLMAP and nerfstudio loaders.
"""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from cusgs_jax.testing.scenes import axis_angle_rotation

W, H, N_VIEWS = 64, 48, 8
BACKGROUND, MARKER, SIGMA = 200.0, -180.0, 1.2  # markers are dark dips in one channel
CAMERAS = {  # model: params for a 64×48 image
    "SIMPLE_RADIAL": (50.0, 32.0, 24.0, 0.08),  # pincushion: the undistorted image shrinks
    "RADIAL": (50.0, 31.6, 24.3, -0.1, 0.02),  # barrel: it grows
    "OPENCV": (50.0, 52.0, 32.3, 23.8, -0.12, 0.02, 0.001, -0.002),
    "OPENCV_FISHEYE": (40.0, 41.0, 32.0, 24.0, 0.05, -0.01, 0.0, 0.0),
    # nerfstudio's OPENCV with k3: COLMAP's FULL_OPENCV with the rational part (k4, k5, k6) zero
    "FULL_OPENCV": (50.0, 51.0, 32.1, 24.2, -0.1, 0.03, 0.002, -0.001, 0.02, 0.0, 0.0, 0.0),
}
# 3×2 grid of points at z = 5 in front of the cameras (about ±16 px, ±10 px from the centre).
POINTS = np.array([[x, y, 5.0] for y in (-1.0, 1.0) for x in (-1.6, 0.0, 1.6)])


def render_through(cam, rot, t, uniform=False) -> np.ndarray:
    """[H, W, 3] uint8 image through the distorted ``cam`` (markers around the points' rays)."""
    img = np.full((cam.height, cam.width, 3), BACKGROUND)
    if not uniform:
        jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        rays = cam.cam_from_img(np.stack([jj.ravel(), ii.ravel()], -1)).reshape(cam.height, cam.width, 2)
        pc = POINTS @ rot.T + t
        fx, fy = cam.focal_length_x, cam.focal_length_y  # what COLMAP's undistorted camera keeps
        for p, (x, y, z) in enumerate(pc):
            d2 = ((rays[..., 0] - x / z) * fx) ** 2 + ((rays[..., 1] - y / z) * fy) ** 2
            img[..., p % 3] += MARKER * np.exp(-0.5 * d2 / SIGMA**2)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def distorted_colmap_scene(root, cameras, *, uniform=False, seed=0, subfolder=False, ext=".png"):
    """Write a distorted scene under ``root``: image i uses camera i % len(cameras), where
    ``cameras`` = [(model, params), ...] (all W×H); ``ext``: the image files' extension
    (JPEGs at quality 100 without chroma subsampling). Returns {name: (R, t)}."""
    rng = np.random.default_rng(seed)
    import pycolmap

    rec = pycolmap.Reconstruction()
    cams = []
    for cid, (model, params) in enumerate(cameras, start=1):
        cam = pycolmap.Camera(camera_id=cid, model=model, width=W, height=H, params=list(params))
        rec.add_camera_with_trivial_rig(cam)
        cams.append(cam)
    poses = {}
    for i in range(N_VIEWS):
        name = (f"cam{i % 2}/" if subfolder else "") + f"v{i:02d}{ext}"
        rot = axis_angle_rotation(rng.uniform(-0.05, 0.05, 3))
        t = rng.uniform(-0.2, 0.2, 3)
        cam = cams[i % len(cams)]
        keypoints = cam.img_from_cam(POINTS @ rot.T + t)
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=cam.camera_id, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(rot), t))
        (root / "images" / name).parent.mkdir(parents=True, exist_ok=True)
        kwargs = dict(quality=100, subsampling=0) if ext == ".jpg" else {}
        iio.imwrite(root / "images" / name, render_through(cam, rot, t, uniform), **kwargs)
        poses[name] = (rot, t)
    for p, xyz in enumerate(POINTS):
        track = pycolmap.Track()
        for i in range(N_VIEWS):
            track.add_element(i + 1, p)
        rec.add_point3D(xyz, track, np.array([255, 0, 0], np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    return poses


def marker_errors(scene) -> list[float]:
    """Distance (px) between each marker's intensity centroid in the loaded images and the
    pinhole projection of its point with the loaded K and viewmat (markers ≥ 5 px inside)."""
    errors = []
    for img, K, view in zip(scene.images, scene.Ks.astype(np.float64), scene.viewmats):
        pc = POINTS @ view[:3, :3].T + view[:3, 3]
        uv = (pc @ K.T)[:, :2] / pc[:, 2:]
        for p, (u, v) in enumerate(uv):
            if not (5 <= u <= scene.width - 5 and 5 <= v <= scene.height - 5):
                continue
            j0, i0 = int(u), int(v)
            ii, jj = np.mgrid[i0 - 4:i0 + 5, j0 - 4:j0 + 5]
            w = np.clip(BACKGROUND - img[ii, jj, p % 3].astype(np.float64), 0, None)
            cu, cv = (w * (jj + 0.5)).sum() / w.sum(), (w * (ii + 0.5)).sum() / w.sum()
            errors.append(float(np.hypot(cu - u, cv - v)))
    return errors


def nerfstudio_copy(colmap_root, dst):
    """The distorted COLMAP scene ``colmap_root`` (:func:`distorted_colmap_scene`) as a nerfstudio
    scene in ``dst``: the same images under ``images/`` and a ``transforms.json`` with each frame's
    ``camera_model`` (OPENCV / OPENCV_FISHEYE; PINHOLE cameras as OPENCV without distortion, FULL_OPENCV as OPENCV
    with its k3),
    ``fl_x fl_y cx cy w h``, its distortion keys and an OpenGL camera-to-world ``transform_matrix``
    (what ``ns-process-data`` writes). Returns ``dst``."""
    import json
    import pathlib
    import shutil

    import pycolmap

    colmap_root, dst = pathlib.Path(colmap_root), pathlib.Path(dst)
    shutil.copytree(colmap_root / "images", dst / "images")
    rec = pycolmap.Reconstruction(str(colmap_root / "sparse" / "0"))
    keys = {"OPENCV": ("k1", "k2", "p1", "p2"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"), "PINHOLE": (),
            "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3")}  # its k4–k6 (rational) are zero here
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        cam = rec.cameras[image.camera_id]
        model = cam.model.name
        params = [float(v) for v in cam.params]
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        w2c = np.eye(4)
        w2c[:3] = pose.matrix()
        c2w = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV → OpenGL camera axes
        frame = dict(file_path=f"images/{image.name}", transform_matrix=c2w.tolist(),
                     camera_model="OPENCV" if model in ("PINHOLE", "FULL_OPENCV") else model, w=int(cam.width),
                     h=int(cam.height),
                     fl_x=params[0], fl_y=params[1], cx=params[2], cy=params[3])
        frame.update(zip(keys[model], params[4:]))
        frames.append(frame)
    (dst / "transforms.json").write_text(json.dumps(dict(frames=frames), indent=1))
    return dst
