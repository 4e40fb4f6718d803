"""Tiny Blender (NeRF-synthetic) and nerfstudio scene folders for the tests of :mod:`cusgs_jax.data.layouts`.

Poses are built with an OpenGL look-at (x right, y up, the camera looks along −z), as Blender and
nerfstudio store them; :func:`opencv_look_at` builds the same camera independently in the
project's convention (world→camera, OpenCV axes) for closed-form checks.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np

__all__ = ["gl_look_at", "opencv_look_at", "orbit_eyes", "write_blender_scene", "write_nerfstudio_scene",
           "write_ply_points"]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def gl_look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] camera-to-world, OpenGL camera axes (columns: right, up, backward; eye)."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    forward = _unit(target - eye)
    right = _unit(np.cross(forward, up))
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def opencv_look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world→camera, OpenCV axes (rows: right, down, forward), built without OpenGL."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    z = _unit(target - eye)
    x = _unit(np.cross(z, up))
    y = np.cross(z, x)  # down in the image
    view = np.eye(4)
    view[:3, :3] = np.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def orbit_eyes(n: int, radius: float = 4.0, seed: int = 0) -> np.ndarray:
    """[n, 3] camera positions on a sphere of ``radius`` around the origin (upper hemisphere, z up)."""
    rng = np.random.default_rng(seed)
    azimuth = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.3)
    elevation = rng.uniform(0.2, 0.9, n)
    return radius * np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation)], axis=-1)


def _image(rng, width: int, height: int, channels: int) -> np.ndarray:
    return rng.integers(0, 256, (height, width, channels), dtype=np.uint8)


def write_blender_scene(root, *, train: int = 4, test: int = 2, width: int = 16, height: int = 12,
                        angle_x: float = 0.69, radius: float = 4.0, rgba: bool = True, seed: int = 0,
                        with_val: bool = True) -> dict:
    """Write ``root/transforms_{train,test,val}.json`` and RGBA (or RGB) PNGs ``train/r_i.png``, ``test/r_i.png``.

    ``file_path`` is written NeRF-synthetic style, ``./train/r_0`` (no extension).

    Returns:
      {"root", "names": [train names then test names], "c2w": [V, 4, 4] OpenGL, "images": [V, H, W, C] uint8,
       "angle_x", "width", "height"}.
    """
    import imageio.v3 as iio

    root = pathlib.Path(root)
    rng = np.random.default_rng(seed)
    eyes = orbit_eyes(train + test + (2 if with_val else 0), radius, seed)
    names, c2ws, images = [], [], []
    splits = [("train", train), ("test", test)] + ([("val", 2)] if with_val else [])
    k = 0
    for split, count in splits:
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in range(count):
            c2w = gl_look_at(eyes[k])
            k += 1
            pixels = _image(rng, width, height, 4 if rgba else 3)
            if rgba:
                pixels[0, 0, 3], pixels[0, 1, 3] = 0, 255  # a transparent and an opaque pixel at least
            iio.imwrite(root / split / f"r_{i}.png", pixels)
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.1, "transform_matrix": c2w.tolist()})
            if split != "val":
                names.append(f"{split}/r_{i}.png")
                c2ws.append(c2w)
                images.append(pixels)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames}))
    return dict(root=root, names=names, c2w=np.stack(c2ws), images=np.stack(images), angle_x=angle_x,
                width=width, height=height)


def write_ply_points(path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """A PLY with vertex x y z (float32) and, when given, red green blue (uint8)."""
    from plyfile import PlyData, PlyElement

    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")] + ([("red", "u1"), ("green", "u1"), ("blue", "u1")]
                                                        if colors is not None else [])
    data = np.empty(len(points), dtype=fields)
    for i, c in enumerate("xyz"):
        data[c] = points[:, i]
    if colors is not None:
        for i, c in enumerate(("red", "green", "blue")):
            data[c] = colors[:, i]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))


def write_nerfstudio_scene(root, *, n: int = 6, width: int = 16, height: int = 12, fl=(14.0, 15.0), c=(8.0, 6.5),
                           camera_model: str | None = "OPENCV", distortion: dict | None = None,
                           per_frame_intrinsics: bool = False, ply: bool = False, radius: float = 3.0,
                           seed: int = 0, channels: int = 3, prescaled: int = 0) -> dict:
    """Write ``root/transforms.json`` (frames in a shuffled order) and PNGs ``images/frame_XXXXX.png``.

    Args:
      distortion: top-level k1 k2 k3 k4 p1 p2 (default all zero).
      per_frame_intrinsics: write fl_x fl_y cx cy w h in every frame instead of the top level.
      ply: also write ``sparse_pc.ply`` with 50 points and colours, named by ``ply_file_path``.
      prescaled: also write ``images_{prescaled}/`` copies downscaled by that factor (box filter).
    Returns:
      {"root", "names" (sorted), "c2w" [V, 4, 4] OpenGL by sorted name, "images" [V, H, W, C],
       "points", "colors" (with ``ply``), "meta" (the JSON written)}.
    """
    import imageio.v3 as iio

    root = pathlib.Path(root)
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    eyes = orbit_eyes(n, radius, seed)
    intrinsics = dict(fl_x=fl[0], fl_y=fl[1], cx=c[0], cy=c[1], w=width, h=height)
    frames, names, c2ws, images = [], [], [], []
    for i in range(n):
        name = f"images/frame_{i + 1:05d}.png"
        pixels = _image(rng, width, height, channels)
        iio.imwrite(root / name, pixels)
        if prescaled:
            (root / f"images_{prescaled}").mkdir(exist_ok=True)
            small = pixels.reshape(height // prescaled, prescaled, width // prescaled, prescaled, -1).mean((1, 3))
            iio.imwrite(root / f"images_{prescaled}" / pathlib.Path(name).name, small.round().astype(np.uint8))
        c2w = gl_look_at(eyes[i])
        frame = {"file_path": name, "transform_matrix": c2w.tolist(), "colmap_im_id": i + 1}
        if per_frame_intrinsics:
            frame.update(intrinsics)
        frames.append(frame)
        names.append(name)
        c2ws.append(c2w)
        images.append(pixels)
    meta: dict = {} if per_frame_intrinsics else dict(intrinsics)
    if camera_model is not None:
        meta["camera_model"] = camera_model
    meta.update(dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0) if distortion is None else distortion)
    meta["frames"] = [frames[i] for i in rng.permutation(n)]
    meta["applied_transform"] = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]]
    out = dict(root=root, names=names, c2w=np.stack(c2ws), images=np.stack(images), meta=meta)
    if ply:
        points = rng.normal(size=(50, 3))
        colors = rng.integers(0, 256, (50, 3), dtype=np.uint8)
        write_ply_points(root / "sparse_pc.ply", points, colors)
        meta["ply_file_path"] = "sparse_pc.ply"
        out.update(points=points, colors=colors)
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out
