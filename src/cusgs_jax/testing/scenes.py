"""Small random inputs for the tests: Gaussian scenes (float64 NumPy) for the splatting tests,
SfM-like point clouds and PSC banks for the training tests."""

from __future__ import annotations

import numpy as np

__all__ = ["KEYS", "as_dtype", "feature_maps", "make_scene", "object_scene", "random_banks", "sfm_points",
           "transformed_scene"]

KEYS = ("means", "quats", "scales", "opacities", "colors")
"""The Gaussian parameter keys of a scene, in rasteriser argument order."""


def axis_angle_rotation(axis_angle) -> np.ndarray:
    """[3, 3] float64 rotation of the axis-angle vector [3] (Rodrigues; independent of pycolmap)."""
    v = np.asarray(axis_angle, np.float64)
    theta = np.linalg.norm(v)
    if theta == 0:
        return np.eye(3)
    k = v / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def random_rotation(seed) -> np.ndarray:
    """[3, 3] float64 proper rotation (det +1) from the QR decomposition of a seeded normal matrix."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def make_scene(seed=0, num=120, width=40, height=28, channels=3, *, behind=0, offscreen=0,
               opaque=0, focal=None, depth_range=(1.0, 6.0)):
    """Random Gaussians in a camera frustum, as float64 NumPy arrays.

    Args:
      behind: how many Gaussians to put behind the camera / in front of `near`.
      offscreen: how many to put far outside the frustum.
      opaque: how many get opacity 1 (alpha clamped at 0.999).
    Returns:
      dict with means [G,3], quats [G,4], scales [G,3], opacities [G],
      colors [G,C], viewmat [4,4], K [3,3], background [C], width, height.
    """
    rng = np.random.default_rng(seed)
    focal = focal or 0.9 * width
    z = rng.uniform(*depth_range, num)
    x = rng.uniform(-0.6, 0.6, num) * z * width / focal
    y = rng.uniform(-0.6, 0.6, num) * z * height / focal
    means = np.stack([x, y, z], -1)
    if behind:
        means[:behind, 2] = rng.uniform(-2.0, 0.009, behind)
    if offscreen:
        means[behind:behind + offscreen, 0] = rng.choice([-1, 1], offscreen) * rng.uniform(20, 40, offscreen)
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.25), (num, 3)))
    opacities = rng.uniform(0.05, 0.95, num)
    opacities[num - opaque:] = 1.0
    # A rotated, translated camera: world = camera frame rotated about y by 10°.
    angle = np.deg2rad(10.0)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    center = np.array([0.3, -0.2, -0.5])
    means = means @ rot.T + center  # camera→world
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot.T
    viewmat[:3, 3] = -rot.T @ center
    K = np.array([[focal, 0, width / 2], [0, focal * 1.05, height / 2], [0, 0, 1]])
    return dict(
        means=means, quats=rng.normal(size=(num, 4)), scales=scales, opacities=opacities,
        colors=rng.uniform(0, 1, (num, channels)), viewmat=viewmat, K=K,
        background=rng.uniform(0, 1, channels), width=width, height=height,
    )


def as_dtype(scene, dtype):
    """Scene arrays cast to `dtype` (ints untouched)."""
    return {k: (np.asarray(v, dtype) if isinstance(v, np.ndarray) else v) for k, v in scene.items()}


def sfm_points(num: int = 400, seed: int = 0) -> np.ndarray:
    """[P, 3] float64 points uniform in the box [-1, 1]² × [2, 4] (in front of an identity camera)."""
    points = np.random.default_rng(seed).uniform(-1, 1, (num, 3))
    points[:, 2] += 3.0
    return points


def random_banks(shapes: dict[str, tuple[int, int]], seed: int = 1) -> dict[str, np.ndarray]:
    """{model: [M, D] float32 standard-normal PSC entries}, drawn in the order of ``shapes``."""
    rng = np.random.default_rng(seed)
    return {name: rng.normal(size=shape).astype(np.float32) for name, shape in shapes.items()}


def feature_maps(n: int = 3, h: int = 5, w: int = 7, d: int = 4, seed: int = 0) -> np.ndarray:
    """[n, h, w, d] float32 standard-normal feature maps with a zero ("no target") pixel in
    view 0 and, when n > 1 and h > 2, a zero row in view 1."""
    maps = np.random.default_rng(seed).normal(size=(n, h, w, d)).astype(np.float32)
    maps[0, 0, 0] = 0.0
    if n > 1 and h > 2:
        maps[1, 2, :] = 0.0
    return maps


def transformed_scene(src, dst, *, scale: float, translation=(0.0, 0.0, 0.0), rotation_xyzw=(0.0, 0.0, 0.0, 1.0)):
    """A copy of the COLMAP scene ``src`` (images and model) under the similarity ``x → s·R·x + t``.

    The same capture as another SfM run might have reconstructed it (pycolmap's
    ``Reconstruction.transform``). Returns the new scene folder ``dst``.
    """
    import pathlib
    import shutil

    import pycolmap

    src, dst = pathlib.Path(src), pathlib.Path(dst)
    shutil.copytree(src / "images", dst / "images")
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    rotation = np.asarray(rotation_xyzw, np.float64) / np.linalg.norm(rotation_xyzw)
    rec.transform(pycolmap.Sim3d(float(scale), pycolmap.Rotation3d(rotation), np.asarray(translation, np.float64)))
    (dst / "sparse" / "0").mkdir(parents=True)
    rec.write(str(dst / "sparse" / "0"))
    return dst


def object_scene(dst, *, views: int = 8, width: int = 32, height: int = 24, num_points: int = 300,
                 seed: int = 0, facing_away: bool = False):
    """A small object seen whole by every camera: a COLMAP text model plus images.

    ``num_points`` SfM points fill a ball of radius 0.5 at the origin; ``views``
    cameras on a ring of radius 4 (height 1) look at it with a focal length that
    keeps the ball inside every image, so every anchor is visible in every view
    (the 360° case where a frustum gather can skip nothing). Each image paints
    the points' colours over grey. ``facing_away`` turns every camera round (half a turn about its
    y axis, same centre): the ball is then behind every camera and the images are plain grey, as
    poses read in the wrong convention would leave it. Returns the scene folder ``dst``.
    """
    import pathlib

    import imageio.v3 as iio
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    dst = pathlib.Path(dst)
    model, images = dst / "sparse" / "0", dst / "images"
    model.mkdir(parents=True)
    images.mkdir(parents=True)
    direction = rng.normal(size=(num_points, 3))
    points = 0.5 * direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0, 1, (num_points, 1))
    colors = rng.integers(0, 256, (num_points, 3))
    focal = 0.8 * width
    (model / "cameras.txt").write_text(f"1 PINHOLE {width} {height} {focal} {focal} {width / 2} {height / 2}\n")
    lines = []
    for v in range(views):
        angle = 2 * np.pi * v / views
        eye = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        rot = np.stack([right, np.cross(forward, right), forward])  # OpenCV: x right, y down, z forward
        if facing_away:
            rot = np.diag([-1.0, 1.0, -1.0]) @ rot
        trans = -rot @ eye
        x, y, z, w = Rotation.from_matrix(rot).as_quat()
        name = f"view_{v:03d}.png"
        lines.append(f"{v + 1} {w} {x} {y} {z} {trans[0]} {trans[1]} {trans[2]} 1 {name}\n\n")
        cam = points @ rot.T + trans
        u = np.clip((focal * cam[:, 0] / cam[:, 2] + width / 2).astype(int), 0, width - 1)
        r = np.clip((focal * cam[:, 1] / cam[:, 2] + height / 2).astype(int), 0, height - 1)
        image = np.full((height, width, 3), 128, np.uint8)
        order = np.argsort(-cam[:, 2])  # far to near: nearer points paint over
        order = order[cam[order, 2] > 0]  # only points in front of the camera
        image[r[order], u[order]] = colors[order]
        iio.imwrite(images / name, image)
    (model / "images.txt").write_text("".join(lines))
    (model / "points3D.txt").write_text("".join(
        f"{i + 1} {p[0]} {p[1]} {p[2]} {c[0]} {c[1]} {c[2]} 0.5\n" for i, (p, c) in enumerate(zip(points, colors))))
    return dst
