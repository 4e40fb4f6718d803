"""The demo's furniture without the room, as an object-centric capture in two layouts.

:mod:`cusgs_jax.data.demo` renders a closed room. This module renders only the furniture group in
the middle of it — the table (top and legs), the three boxes on it, the chair and the box on the
floor beside the table (the cabinet, shelf and bench stand against the walls and are left out) —
with **no walls, floor or ceiling**, an alpha channel (transparent where no object is hit), from
cameras on the upper hemisphere around the group, NeRF-synthetic style. The same renders are written
twice, so a run on each differs only in how it is initialised:

``OUT/blender/``  Blender / NeRF-synthetic layout: ``transforms_train.json`` (the training views),
    ``transforms_test.json`` (the held-out views), ``camera_angle_x``, OpenGL camera-to-world
    matrices, RGBA PNGs ``train/r_XXX.png`` / ``test/r_XXX.png``; no points (a run starts from
    ``data.random_points``).
``OUT/colmap/``   COLMAP layout: ``images/view_XXX.png`` — the same RGBA composited on white
    exactly as the Blender loader composites them (``round(rgb·a + 255·(1 − a))``, so both loaders
    give byte-identical images) — and ``sparse/0/`` with one PINHOLE camera of the same focal
    length and SfM-style points sampled on the visible object surfaces (seen in ≥ 2 views, from all
    views, as SfM would; :mod:`cusgs_jax.data.demo.sfm`).

View ``k`` (of ``num_views``) is ``view_{k:03d}.png`` in COLMAP and ``r_{k:03d}.png`` in Blender;
the held-out views are those with ``k % holdout_every == 0`` — exactly what the COLMAP loader holds
out with ``data.holdout_every=<holdout_every>`` (it sorts by name and holds out index ``i %
holdout_every == 0``), so both layouts are evaluated on the same views. Defaults: 70 views,
``holdout_every=7`` → 60 train / 10 test.

Cameras: centre ``c`` = the middle of the group's bounding box; eye directions area-uniform on the
upper hemisphere between 8° and 80° of elevation (deterministic from ``seed``), at ``radius`` from
``c``, looking at ``c`` with z up and no roll; ``camera_angle_x`` 0.6911 rad (NeRF-synthetic's),
square pixels, principal point at the centre: ``fx = fy = 0.5·W / tan(0.5·camera_angle_x)``.
Colour: 2×2 supersampling; RGB is the mean over the sub-samples that hit an object (straight
alpha), alpha the fraction that hit. World frame and units are the demo room's (z up, metres).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import warnings

import numpy as np

from cusgs_jax.data.demo.sfm import write_sfm_model
from cusgs_jax.data.demo.render import camera_rays, look_at, build_scene, cast_rays, surface_colour

__all__ = ["OBJECTS", "ANGLE_X", "build_objects_scene", "object_cameras", "render_rgba",
           "generate_object_scenes"]

# The furniture group around the table (names of demo.render._OBJECTS).
OBJECTS = ("table_top", "table_legs", "box_cat", "box_tall", "box_flat", "box_floor", "chair")
ANGLE_X = 0.6911112070083618  # NeRF-synthetic's camera_angle_x
_SUBSAMPLES = [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]


def build_objects_scene():
    """The demo scene (:func:`~cusgs_jax.data.demo.render.build_scene`) reduced to :data:`OBJECTS`:
    the room box and every other object's boxes (and their six faces each) removed; face ids are
    re-indexed ``6 * box + ...`` over the kept boxes, object ids, textures and shading unchanged."""
    full = build_scene()
    ids = {o["id"] for o in full.objects if o["name"] in OBJECTS}
    face_obj = full.face_obj.reshape(-1, 6)
    keep = np.flatnonzero(~full.box_inside & np.isin(face_obj[:, 0], list(ids)))
    faces = (6 * keep[:, None] + np.arange(6)).reshape(-1)
    return dataclasses.replace(
        full, box_lo=full.box_lo[keep], box_hi=full.box_hi[keep], box_inside=full.box_inside[keep],
        face_origin=full.face_origin[faces], face_e1=full.face_e1[faces], face_e2=full.face_e2[faces],
        face_obj=full.face_obj[faces], face_tex=full.face_tex[faces], face_shade=full.face_shade[faces],
        face_area=full.face_area[faces], objects=[o for o in full.objects if o["id"] in ids])


def object_cameras(scene, num_views: int, seed: int, radius: float):
    """``num_views`` world→camera OpenCV poses ``[(R, t), ...]`` on the upper hemisphere (module docstring)."""
    centre = 0.5 * (scene.box_lo.min(axis=0) + scene.box_hi.max(axis=0))
    rng = np.random.default_rng([seed, 7])
    lo, hi = np.sin(np.deg2rad(8.0)), np.sin(np.deg2rad(80.0))
    # stratified azimuths (random order) so neighbouring training views overlap everywhere
    azimuth = 2 * np.pi * (rng.permutation(num_views) + rng.uniform(0, 1, num_views)) / num_views
    elevation = np.arcsin(rng.uniform(lo, hi, num_views))  # area-uniform on the band
    poses = []
    for az, el in zip(azimuth, elevation):
        eye = centre + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        R = look_at(eye, centre, 0.0)
        poses.append((R, -R @ eye))
    return poses, centre


def render_rgba(scene, R, t, width, height, K):
    """Ray-cast one view with alpha.

    Returns:
      rgba uint8 [H, W, 4] (straight alpha; RGB 0 where alpha is 0), depth float32 [H, W] (camera z
      of the pixel-centre ray, 0 = none) and face ids int64 [H, W] (-1 = none).
    """
    centre = -R.T @ t
    (d_c,) = camera_rays(R, width, height, K, [(0.5, 0.5)])
    tc, fc = cast_rays(scene, centre, d_c)
    depth = np.where(fc >= 0, tc, 0.0).astype(np.float32).reshape(height, width)
    colour = np.zeros((width * height, 3))
    hits = np.zeros(width * height)
    for d in camera_rays(R, width, height, K, _SUBSAMPLES):
        ts, fs = cast_rays(scene, centre, d)
        ok = fs >= 0
        colour[ok] += surface_colour(scene, centre + ts[ok, None] * d[ok], fs[ok])
        hits += ok
    rgb = colour / np.maximum(hits, 1)[:, None]
    alpha = hits / len(_SUBSAMPLES)
    rgba = np.concatenate([np.clip(rgb, 0, 1), alpha[:, None]], axis=-1)
    rgba = np.round(rgba * 255.0).astype(np.uint8).reshape(height, width, 4)
    return rgba, depth, fc.reshape(height, width)


def composite_white(rgba: np.ndarray) -> np.ndarray:
    """uint8 [H, W, 4] → uint8 [H, W, 3] on white, the Blender loader's formula
    (:func:`cusgs_jax.data.images.to_rgb_uint8`): ``round(rgb·a + 255·(1 − a))``, ``a = alpha/255``."""
    a = rgba[..., 3:].astype(np.float64) / 255.0
    out = rgba[..., :3].astype(np.float64) * a + 255.0 * (1.0 - a)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def generate_object_scenes(out_dir, *, num_views: int = 70, holdout_every: int = 7, width: int = 128,
                           height: int = 128, radius: float = 4.5, num_points: int = 6000,
                           seed: int = 0) -> dict:
    """Write ``out_dir/blender`` and ``out_dir/colmap`` (module docstring) from the same renders.

    Args:
      num_views: all views; ``k % holdout_every == 0`` are the test views (Blender's transforms_test,
        COLMAP's ``data.holdout_every=holdout_every``).
      width, height: image size; ``radius``: camera distance from the group's centre.
      num_points: surface samples for the COLMAP points (only those seen in ≥ 2 views are kept).
      seed: cameras and point sampling.
    Returns:
      {"blender": Path, "colmap": Path, "train": [k], "test": [k], "num_points": P, "centre": [3]}.
    Raises:
      FileExistsError when ``out_dir/blender`` or ``out_dir/colmap`` exists.
    """
    import imageio.v3 as iio

    if num_views < 2 or holdout_every < 2 or width < 2 or height < 2 or num_points < 1:
        raise ValueError("need num_views >= 2, holdout_every >= 2, width/height >= 2, num_points >= 1")
    out = pathlib.Path(out_dir)
    blender, colmap = out / "blender", out / "colmap"
    for d in (blender, colmap):
        if d.exists():
            raise FileExistsError(f"{d} exists; remove it or choose another folder")
    scene = build_objects_scene()
    focal = 0.5 * width / math.tan(0.5 * ANGLE_X)
    K = (focal, focal, width / 2.0, height / 2.0)
    poses, centre = object_cameras(scene, num_views, seed, radius)
    test = [k for k in range(num_views) if k % holdout_every == 0]
    train = [k for k in range(num_views) if k % holdout_every]
    (colmap / "images").mkdir(parents=True)
    depths, face_maps = [], []
    frames = {"train": [], "test": []}
    for k, (R, t) in enumerate(poses):
        rgba, depth, faces = render_rgba(scene, R, t, width, height, K)
        depths.append(depth)
        face_maps.append(faces)
        split = "test" if k % holdout_every == 0 else "train"
        (blender / split).mkdir(parents=True, exist_ok=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            iio.imwrite(blender / split / f"r_{k:03d}.png", rgba)
            iio.imwrite(colmap / "images" / f"view_{k:03d}.png", composite_white(rgba))
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = R, t
        c2w = np.linalg.inv(view) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV → OpenGL camera axes
        frames[split].append({"file_path": f"./{split}/r_{k:03d}", "transform_matrix": c2w.tolist()})
    for split, fr in frames.items():
        (blender / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": ANGLE_X, "frames": fr}, indent=1) + "\n")

    names = [f"view_{k:03d}.png" for k in range(num_views)]
    xyz, visible = write_sfm_model(colmap / "sparse" / "0", scene, poses, K, width, height, names, depths, face_maps,
                                   num_points, seed)
    info = {"generator": "cusgs_jax.data.demo.objects", "objects": list(OBJECTS), "num_views": num_views,
            "holdout_every": holdout_every, "width": width, "height": height, "radius": radius,
            "camera_angle_x": ANGLE_X, "seed": seed, "num_points": int(xyz.shape[0]),
            "centre": centre.tolist(), "train": train, "test": test}
    for d in (blender, colmap):
        (d / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    return dict(info, blender=blender, colmap=colmap)
