"""The built-in demo scene: a small synthetic textured room, written as a real COLMAP model.

Everything is generated in NumPy from scratch (no downloads) and is deterministic for a given
set of parameters. The scene is a closed room (floor, four walls, ceiling, seen from inside)
furnished with a table, boxes, a chair, a cabinet, a shelf and a bench. Every object is made of
axis-aligned boxes and is textured with a different photograph that ships inside scikit-image,
stretched once over each face (no tiling). Surfaces are Lambertian: a fixed per-face shading
factor (from the face's normal) but nothing view-dependent, so a surface point has the same
colour from every view.

Conventions
-----------
* World frame: metres-ish units, **z up**; the room spans x, y in [-3, 3] and z in [0, 3]; the
  table top centre is near (0, 0, 0.78).
* Cameras: OpenCV convention (x right, y down, z forward). Poses are world->camera
  ``x_cam = R @ x_world + t`` (COLMAP's ``cam_from_world``). Intrinsics are PINHOLE with
  ``fx = fy = 0.8 * width``, ``cx = width / 2``, ``cy = height / 2``; pixel ``(i, j)`` (row,
  column) covers ``[j, j+1] x [i, i+1]`` and its centre is ``(j + 0.5, i + 0.5)`` - the COLMAP
  convention, so a 3D point projects to ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.

Folder layout written by :func:`generate_demo_scene`::

    OUT/images/view_000.png ...      uint8 RGB [H, W, 3]
    OUT/sparse/0/cameras.bin, images.bin, points3D.bin (+ rigs.bin, frames.bin)  COLMAP binary
    OUT/depth/view_000.npy ...       float32 [H, W]: camera-space z of the visible surface, 0 = none
    OUT/object_ids/view_000.npy ...  uint8 [H, W]: object id of the visible surface, 0 = none
    OUT/objects.json                 [{"id", "name", "texture", "boxes"}, ...]
    OUT/scene.json                   generation parameters and summary

Modules: this one (generation, cache folder), :mod:`.demo.render` (room geometry, textures, ray
casting, cameras), :mod:`.demo.sfm` (SfM-like points, observations, COLMAP writing); the
``cusgs-demo-scene`` command is :mod:`cusgs_jax.app.demo_scene`. :mod:`.demo.objects` renders the
furniture without the room, with alpha, from the upper hemisphere, in Blender and COLMAP layouts
(an object-centric scene for random initialisation); :mod:`.demo.lens` renders the room
through a distorting COLMAP lens (``data.demo.lens``).
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import tempfile
import time
import warnings

import numpy as np

from cusgs_jax.cache import default_cache_dir
from cusgs_jax.data.demo.sfm import write_sfm_model
from cusgs_jax.data.demo.render import (
    ROOM,
    TABLE_CENTRE,
    build_scene,
    make_cameras,
    render_view,
)

__all__ = ["FORMAT_VERSION", "cached_scene", "demo_scene_path", "generate_demo_scene"]

FORMAT_VERSION = 3  # 2: SfM points sampled from observed pixels; 3: cameras never see the ceiling
FOCAL_FACTOR = 0.8  # fx = fy = FOCAL_FACTOR * width (horizontal FOV ~64 deg)
_OUTPUTS = ("images", "sparse", "depth", "object_ids", "masked", "objects.json", "scene.json")


def generate_demo_scene(out_dir, *, seed=0, num_views=30, width=160, height=120, num_points=6000,
                        overwrite=False) -> pathlib.Path:
    """Generate the synthetic demo room into ``out_dir`` and return it as a Path.

    Writes ``images/view_XXX.png`` (uint8 RGB [height, width, 3]), ``sparse/0/`` (COLMAP binary
    model: one PINHOLE camera, ``num_views`` posed images, points3D with tracks and the matching
    2D keypoints), ``depth/view_XXX.npy`` (float32 [height, width], camera-space z, 0 = no
    surface), ``object_ids/view_XXX.npy`` (uint8 [height, width], 0 = none), ``objects.json`` and
    ``scene.json``.

    Args:
      out_dir: output folder; created if missing. If it already holds a scene (any of the output
        entries above) and ``overwrite`` is False, FileExistsError is raised; with ``overwrite``
        only those entries are replaced (nothing else in the folder is touched).
      seed: seeds the camera jitter and the point sampling (the room itself is fixed).
      num_views: number of cameras orbiting the table.
      width, height: image size in pixels; fx = fy = 0.8 * width, principal point at the centre.
      num_points: number of surface samples; only those seen in >= 2 views are kept, so the
        model holds at most this many points.
    Returns:
      pathlib.Path of ``out_dir``.
    """
    if num_views < 2 or width < 2 or height < 2 or num_points < 1:
        raise ValueError("need num_views >= 2, width/height >= 2 and num_points >= 1")
    out = pathlib.Path(out_dir)
    clear_outputs(out, overwrite)

    t0 = time.perf_counter()
    scene = build_scene()
    K = (FOCAL_FACTOR * width, FOCAL_FACTOR * width, width / 2.0, height / 2.0)
    poses = make_cameras(scene, num_views, seed)
    names = [f"view_{v:03d}.png" for v in range(num_views)]
    depths, face_maps = _write_views(out, scene, poses, names, width, height, K)

    xyz, visible = write_sfm_model(out / "sparse" / "0", scene, poses, K, width, height, names, depths, face_maps,
                                   num_points, seed)

    (out / "objects.json").write_text(json.dumps(scene.objects, indent=1) + "\n")
    track_len = visible.sum(axis=0)
    info = {
        "generator": "cusgs_jax.data.demo", "format_version": FORMAT_VERSION,
        "seed": seed, "num_views": num_views, "width": width, "height": height,
        "num_points_sampled": num_points, "num_points": int(xyz.shape[0]),
        "mean_track_length": float(track_len.mean()) if track_len.size else 0.0,
        "camera_model": "PINHOLE", "intrinsics": {"fx": K[0], "fy": K[1], "cx": K[2], "cy": K[3]},
        "world_up": [0.0, 0.0, 1.0], "room_bounds": [list(ROOM[0]), list(ROOM[1])],
        "look_at": TABLE_CENTRE.tolist(), "images": names,
        "generation_seconds": round(time.perf_counter() - t0, 3),
    }
    (out / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    return out


def clear_outputs(out: pathlib.Path, overwrite: bool) -> None:
    """Remove the scene entries (_OUTPUTS) already in ``out``; FileExistsError if there are any
    and not ``overwrite``. Nothing else in the folder is touched."""
    existing = [e for e in _OUTPUTS if (out / e).exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{out} already contains a scene ({', '.join(existing)}); "
                              "pass overwrite=True to replace it")
    for e in existing:
        shutil.rmtree(out / e) if (out / e).is_dir() else (out / e).unlink()


def _write_views(out: pathlib.Path, scene, poses, names, width, height, K):
    """Ray-cast every view and write ``images/<name>``, ``depth/<stem>.npy`` and
    ``object_ids/<stem>.npy``.

    Returns:
      depths: list of V float32 [H, W] (camera z, 0 = none) and face_maps: list of V int64
      [H, W] face ids (-1 = none), in view order.
    """

    for sub in ("images", "depth", "object_ids"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    depths, face_maps = [], []
    for v, (R, t) in enumerate(poses):
        image, depth, obj, faces = render_view(scene, R, t, width, height, K)
        write_view_files(out, names[v], image, depth, obj)
        depths.append(depth)
        face_maps.append(faces)
    return depths, face_maps


def write_view_files(out: pathlib.Path, name: str, image: np.ndarray, depth: np.ndarray, obj: np.ndarray) -> None:
    """One demo view's files under ``out``: ``images/<name>`` ([H, W, 3] uint8) and the ray-cast
    ``depth/<stem>.npy`` ([H, W] float32) and ``object_ids/<stem>.npy`` ([H, W] uint8) that annotate it."""
    import imageio.v3 as iio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        iio.imwrite(out / "images" / name, image)
    write_view_maps(out, name, depth, obj)


def write_view_maps(out: pathlib.Path, name: str, depth: np.ndarray, obj: np.ndarray) -> None:
    """``out/depth/<stem>.npy`` ([H, W] float32) and ``out/object_ids/<stem>.npy`` ([H, W] uint8) of the
    view ``name`` (folders made when missing)."""
    stem = name[:-4]
    for sub in ("depth", "object_ids"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    np.save(out / "depth" / f"{stem}.npy", depth)
    np.save(out / "object_ids" / f"{stem}.npy", obj)


def demo_scene_folder(cache_dir=None, *, seed=0, num_views=30, width=160, height=120) -> pathlib.Path:
    """Where :func:`demo_scene_path` keeps the demo scene for these parameters (nothing is generated)."""
    root = pathlib.Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return root / f"demo{FORMAT_VERSION}-s{seed}-v{num_views}-{width}x{height}"


def demo_scene_path(cache_dir=None, *, seed=0, num_views=30, width=160, height=120) -> pathlib.Path:
    """Folder of the demo scene for these parameters, generating it on first use.

    The scene lives in ``cache_dir`` (default ``$CUSGS_CACHE_DIR`` or ``~/.cache/cusgs_jax``)
    under ``demo{FORMAT_VERSION}-s{seed}-v{num_views}-{width}x{height}``. It is generated into a temporary
    sibling folder and renamed into place, so an interrupted generation never leaves a partial
    scene behind; an existing complete folder is reused as is.
    """
    final = demo_scene_folder(cache_dir, seed=seed, num_views=num_views, width=width, height=height)
    return cached_scene(final, lambda tmp: generate_demo_scene(
        tmp, seed=seed, num_views=num_views, width=width, height=height, overwrite=True))


def cached_scene(final, generate) -> pathlib.Path:
    """``final`` (a Path) once it holds a complete generated scene (``scene.json``), calling
    ``generate(tmp)`` first when it does not.

    ``generate`` writes the scene into the empty temporary sibling folder ``tmp``, which is then
    renamed to ``final``, so an interrupted generation never leaves a partial scene behind; an
    existing complete folder is reused as is.
    """
    final = pathlib.Path(final)
    root, name = final.parent, final.name
    if (final / "scene.json").is_file():
        return final
    try:
        root.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as error:  # a file where the cache folder (or a parent) should be
        from cusgs_jax.errors import UserError

        raise UserError(f"the demo scene's cache folder {root} cannot be made: {error.filename} is a file, not a "
                        "folder; point CUSGS_CACHE_DIR at a folder (or unset it to use ~/.cache/cusgs_jax)") from None
    prefix = f".{name}.tmp-"
    # Clear temporary folders left behind by interrupted runs (old enough not to be in progress).
    for stale in root.glob(prefix + "*"):
        try:
            if time.time() - stale.stat().st_mtime > 3600:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:
            pass
    if final.exists() and not (final / "scene.json").is_file():
        shutil.rmtree(final)  # an incomplete folder not made by us (e.g. a partial copy)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=prefix, dir=root))
    try:
        generate(tmp)
        try:
            os.replace(tmp, final)
        except OSError:
            if not (final / "scene.json").is_file():  # lost a race only if the winner finished
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final
