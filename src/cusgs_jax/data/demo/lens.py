"""The demo room seen through a distorting lens, ray cast through the lens.

:mod:`cusgs_jax.data.demo` renders the room through a PINHOLE camera. This module renders the
same room, from the same poses, through any COLMAP camera model: the colour of pixel ``(i, j)`` is
the mean over 2×2 sub-pixel samples ``(j + 0.25 | 0.75, i + 0.25 | 0.75)`` of the surface hit by
the ray ``cam_from_img`` of that sample (pycolmap's unprojection of the lens, so the images are
exactly what that lens sees — no image is warped). The depth and object-id maps are per-pixel
annotations of the images *as loaded*, so they are ray cast (pixel centres) through the PINHOLE
camera the loader undistorts the images to (:func:`cusgs_jax.data.undistort.undistorted_cameras`,
e.g. 149×112 for ``opencv`` at 160×120): the ``semantic`` feature model and the retrieval metrics
then line up with the undistorted images. The maps of the other two loading modes are kept beside them:
``masked/`` (:data:`MASKED_MAPS`, the frame of ``data.undistort=mask``) and ``lens/`` (:data:`LENS_MAPS`,
the images as captured, for ``data.undistort=lens``: the pixel-centre rays of the lens itself). The SfM points and their tracks are the pinhole
demo's (same seed → the same points), with every keypoint the lens's projection of its point
(:func:`cusgs_jax.data.demo.sfm.write_sfm_model`). The folder is the demo's layout
(:mod:`cusgs_jax.data.demo`) with ``sparse/0/cameras.bin`` holding the lens's model, so the COLMAP
loader treats it like any distorted capture: rendered through the lens (``data.undistort=lens``, the
default) or undistorted (:mod:`cusgs_jax.data.undistort`).

Ready lenses (:data:`LENSES`, :func:`lens_camera`) for a W×H image, ``f = 0.8·W`` (the demo's):

* ``pinhole``: PINHOLE ``f, f, W/2, H/2`` — the standard demo (its images are the demo's);
* ``opencv``: OPENCV ``fx = 1.02 f, fy = 0.98 f``, principal point ``(0.52 W, 0.48 H)`` (3.2 and
  −2.4 px off centre at 160×120), ``k1 = 0.09, k2 = 0.02, p1 = 0.001, p2 = −0.0015``;
* ``simple_radial``: SIMPLE_RADIAL ``f, W/2, H/2, k = 0.09``.

``k1 > 0`` is pincushion distortion in COLMAP's convention: the lens sees a little less of the
room than the pinhole (the undistorted images are a few pixels smaller, 149×112 for ``opencv`` at
160×120). ``data.demo.lens=<name>`` trains on one (generated once into the cache by
:func:`lens_demo_path`); ``cusgs-demo-scene OUT --lens <name>`` writes one anywhere.
"""

from __future__ import annotations

import json
import pathlib
import time

import numpy as np

from cusgs_jax.cache import default_cache_dir
from cusgs_jax.data.demo.room import (
    FOCAL_FACTOR,
    cached_scene,
    clear_outputs,
    demo_scene_folder,
    demo_scene_path,
    write_view_files,
    write_view_maps,
)
from cusgs_jax.data.demo.sfm import write_sfm_model
from cusgs_jax.data.demo.render import build_scene, cast_rays, make_cameras, mean_colour, render_view
from cusgs_jax.data.undistort import needs_undistortion, undistorted_cameras

__all__ = ["LENSES", "LENS_MAPS", "MASKED_MAPS", "configured_demo", "lens_camera", "lens_demo_folder", "lens_demo_path", "render_lens_view",
           "write_lens_demo"]

LENSES = ("pinhole", "opencv", "simple_radial")
LENS_FORMAT_VERSION = 4  # 2: depth and object ids in the undistorted frame; 3: also in the masked frame; 4: and the lens's
MASKED_MAPS = "masked"  # <scene>/masked/{depth,object_ids}/: the maps in the frame of data.undistort=mask
LENS_MAPS = "lens"  # <scene>/lens/{depth,object_ids}/: the maps of the images as captured (data.undistort=lens)
_SUBSAMPLES = [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]


def lens_camera(lens: str, width: int, height: int) -> tuple[str, list[float]]:
    """(COLMAP model name, params) of the ready lens ``lens`` (one of :data:`LENSES`) for a
    ``width``×``height`` image (module docstring); ValueError for another name."""
    f = FOCAL_FACTOR * width
    cx, cy = width / 2.0, height / 2.0
    if lens == "pinhole":
        return "PINHOLE", [f, f, cx, cy]
    if lens == "opencv":
        return "OPENCV", [1.02 * f, 0.98 * f, 0.52 * width, 0.48 * height, 0.09, 0.02, 0.001, -0.0015]
    if lens == "simple_radial":
        return "SIMPLE_RADIAL", [f, cx, cy, 0.09]
    raise ValueError(f"unknown lens {lens!r}: choose one of {', '.join(LENSES)}")


def _lens_rays(camera, R, offsets):
    """World-space ray directions with camera-space z = 1 through the sub-pixel positions
    ``(j + dx, i + dy)`` of every pixel, unprojected by the lens: [len(offsets), H*W, 3]."""
    w, h = int(camera.width), int(camera.height)
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    out = []
    for dx, dy in offsets:
        xy = camera.cam_from_img(np.stack([(jj + dx).ravel(), (ii + dy).ravel()], -1))
        d_cam = np.concatenate([np.asarray(xy, np.float64), np.ones((xy.shape[0], 1))], -1)
        out.append(d_cam @ R)  # R^T d (row-vector form)
    return np.stack(out)


def render_lens_view(scene, R, t, camera):
    """Ray-cast one view through the lens ``camera`` (a pycolmap Camera, any model).

    Returns:
      image uint8 [H, W, 3] (2×2 supersampled), depth float32 [H, W] (camera z of the pixel-centre
      ray, 0 = none), object ids uint8 [H, W] (0 = none), face ids int64 [H, W] (-1 = none).
    """
    w, h = int(camera.width), int(camera.height)
    centre = -R.T @ t
    (d_c,) = _lens_rays(camera, R, [(0.5, 0.5)])
    tc, fc = cast_rays(scene, centre, d_c)
    hit = fc >= 0
    depth = np.where(hit, tc, 0.0).astype(np.float32).reshape(h, w)
    obj = np.where(hit, scene.face_obj[np.maximum(fc, 0)], 0).astype(np.uint8).reshape(h, w)
    colour = mean_colour(scene, centre, _lens_rays(camera, R, _SUBSAMPLES))
    image = np.round(np.clip(colour, 0.0, 1.0) * 255.0).astype(np.uint8).reshape(h, w, 3)
    return image, depth, obj, fc.reshape(h, w)


def write_lens_demo(out_dir, model: str, params, *, seed=0, num_views=30, width=160, height=120,
                    num_points=6000, overwrite=False, lens_name=None) -> pathlib.Path:
    """Write the demo room seen through the lens ``model``/``params`` into ``out_dir``.

    Same layout, poses and SfM points as :func:`cusgs_jax.data.demo.generate_demo_scene` with the
    same ``seed``, ``num_views``, ``width``, ``height`` and ``num_points``; the images are ray cast
    through the lens, the depth [H', W'] and object-id maps through the undistorted PINHOLE camera
    (W'×H', module docstring), and ``sparse/0/cameras.bin`` holds one camera of the lens's model.

    Args:
      model: a COLMAP camera model name (e.g. ``"OPENCV"``); params: its parameters for a
        ``width``×``height`` image (e.g. :func:`lens_camera`).
      overwrite: as for ``generate_demo_scene`` (FileExistsError when the folder holds a scene).
      lens_name: recorded in ``scene.json`` (``"lens"``) when given.
    Returns:
      pathlib.Path of ``out_dir``.
    """
    import pycolmap

    if num_views < 2 or width < 2 or height < 2 or num_points < 1:
        raise ValueError("need num_views >= 2, width/height >= 2 and num_points >= 1")
    params = [float(p) for p in params]
    try:
        camera = pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=1)
    except Exception as e:  # pycolmap raises ValueError / RuntimeError for bad models
        raise ValueError(f"camera model {model!r} with params {params}: {e}") from e
    if not camera.verify_params():
        raise ValueError(f"camera model {model} takes the params {camera.params_info}, got {params}")
    # the cameras the loader undistorts to (data.undistort=crop, and =mask): the frames of the depth and
    # object-id maps in depth/ and object_ids/, and in masked/depth/ and masked/object_ids/
    distorted = needs_undistortion(camera)
    loaded = undistorted_cameras({1: camera}, mode="crop")[1] if distorted else camera
    masked = undistorted_cameras({1: camera}, mode="mask")[1] if distorted else None
    K_loaded = _intrinsics(loaded)
    out = pathlib.Path(out_dir)
    clear_outputs(out, overwrite)

    t0 = time.perf_counter()
    scene = build_scene()
    K = (FOCAL_FACTOR * width, FOCAL_FACTOR * width, width / 2.0, height / 2.0)  # the pinhole demo's
    poses = make_cameras(scene, num_views, seed)
    names = [f"view_{v:03d}.png" for v in range(num_views)]
    for sub in ("images", "depth", "object_ids"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    pin_depths, pin_faces = [], []
    for v, (R, t) in enumerate(poses):
        image, lens_depth, lens_obj, _ = render_lens_view(scene, R, t, camera)
        _, depth, obj, _ = render_view(scene, R, t, int(loaded.width), int(loaded.height), K_loaded,
                                       supersample=False)
        write_view_files(out, names[v], image, depth, obj)
        if masked is not None:
            write_view_maps(out / LENS_MAPS, names[v], lens_depth, lens_obj)
            _, depth, obj, _ = render_view(scene, R, t, int(masked.width), int(masked.height), _intrinsics(masked),
                                           supersample=False)
            write_view_maps(out / MASKED_MAPS, names[v], depth, obj)
        # the pinhole demo's depth and faces (centre rays only): its SfM points, unchanged
        _, pin_depth, _, faces = render_view(scene, R, t, width, height, K, supersample=False)
        pin_depths.append(pin_depth)
        pin_faces.append(faces)
    xyz, visible = write_sfm_model(out / "sparse" / "0", scene, poses, K, width, height, names, pin_depths,
                                   pin_faces, num_points, seed, lens=(model, params))

    (out / "objects.json").write_text(json.dumps(scene.objects, indent=1) + "\n")
    track_len = visible.sum(axis=0)
    info = {
        "generator": "cusgs_jax.data.demo.lens", "format_version": LENS_FORMAT_VERSION,
        "lens": lens_name, "seed": seed, "num_views": num_views, "width": width, "height": height,
        "num_points_sampled": num_points, "num_points": int(xyz.shape[0]),
        "mean_track_length": float(track_len.mean()) if track_len.size else 0.0,
        "camera_model": model, "camera_params": params,
        "intrinsics": {"fx": float(camera.focal_length_x), "fy": float(camera.focal_length_y),
                       "cx": float(camera.principal_point_x), "cy": float(camera.principal_point_y)},
        "maps_camera": {"model": "PINHOLE", "width": int(loaded.width), "height": int(loaded.height),
                        "params": [float(k) for k in K_loaded],
                        "note": "depth/ and object_ids/ are in the frame of the undistorted images"},
        **({"masked_maps_camera": {"model": "PINHOLE", "width": int(masked.width), "height": int(masked.height),
                                   "params": [float(k) for k in _intrinsics(masked)],
                                   "note": "masked/depth/ and masked/object_ids/ are in the frame of the images "
                                           "undistorted with data.undistort=mask"},
            "lens_maps_camera": {"model": model, "width": width, "height": height, "params": params,
                                 "note": "lens/depth/ and lens/object_ids/ are in the frame of the images as captured "
                                         "(data.undistort=lens), ray cast through the lens at pixel centres"}}
           if masked is not None else {}),
        "images": names, "generation_seconds": round(time.perf_counter() - t0, 3),
    }
    (out / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    return out


def _intrinsics(camera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pycolmap camera."""
    return (camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y)


def lens_demo_folder(cache_dir=None, *, lens="pinhole", seed=0, num_views=30, width=160,
                     height=120) -> pathlib.Path:
    """Where :func:`lens_demo_path` keeps the demo through ``lens`` (nothing is generated): the
    standard demo's folder for ``pinhole``, else ``demo-lens{LENS_FORMAT_VERSION}-<lens>-s…``."""
    if lens == "pinhole":
        return demo_scene_folder(cache_dir, seed=seed, num_views=num_views, width=width, height=height)
    lens_camera(lens, width, height)  # ValueError for an unknown lens
    root = pathlib.Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return root / f"demo-lens{LENS_FORMAT_VERSION}-{lens}-s{seed}-v{num_views}-{width}x{height}"


def lens_demo_path(cache_dir=None, *, lens="pinhole", seed=0, num_views=30, width=160,
                   height=120) -> pathlib.Path:
    """Folder of the demo room through the ready lens ``lens`` (:data:`LENSES`), generating it on
    first use into the cache (as :func:`cusgs_jax.data.demo.demo_scene_path`; ``pinhole`` is the
    standard demo scene itself)."""
    if lens == "pinhole":
        return demo_scene_path(cache_dir, seed=seed, num_views=num_views, width=width, height=height)
    model, params = lens_camera(lens, width, height)
    final = lens_demo_folder(cache_dir, lens=lens, seed=seed, num_views=num_views, width=width, height=height)
    return cached_scene(final, lambda tmp: write_lens_demo(
        tmp, model, params, seed=seed, num_views=num_views, width=width, height=height, overwrite=True,
        lens_name=lens))


def configured_demo(demo, *, generate: bool = False) -> pathlib.Path:
    """The folder of the demo scene a run's ``data.demo`` (:class:`~cusgs_jax.config.DemoConfig`: lens,
    seed, views, size) describes: generated on first use when ``generate`` (:func:`lens_demo_path`),
    else only where it is cached (:func:`lens_demo_folder`)."""
    find = lens_demo_path if generate else lens_demo_folder
    return find(lens=demo.lens, seed=demo.seed, num_views=demo.views, width=demo.width, height=demo.height)
