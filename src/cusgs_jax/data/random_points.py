"""Initial points for scene layouts that come without any (Blender / NeRF-synthetic, nerfstudio without a PLY).

3DGS and Scaffold-GS start NeRF-synthetic scenes from 100 000 points drawn uniformly in the cube
±1.3 around the origin, where the cameras sit on a sphere of radius ~4 looking at it. We need a rule
that gives that for those scenes and something sensible for any other capture, with no scale or
origin assumed:

1. **Centre** ``x``: the point nearest to every camera's optical axis in the least-squares sense,
   ``x = argmin Σ_i ‖(I − d_i d_iᵀ)(x − C_i)‖²`` (``C_i`` the camera centres, ``d_i`` their unit
   viewing directions) — the spot the cameras look at. It is used when the axes are not close to
   parallel (smallest eigenvalue of ``Σ (I − d dᵀ)`` ≥ 0.02·V, about 8° of spread) and ``x`` lies in
   front of the cameras (median depth > 0). Otherwise (a forward-facing capture, a pan) ``x`` is the
   mean camera centre moved along the mean viewing direction by the camera extent (1.1 × the largest
   distance of a camera from the mean centre, 1 when all coincide).
2. **Half-side** ``h``: what the cameras see at their distance, ``h = median_i ‖x − C_i‖ ×
   median_i tan(½ FoV_i)`` with ``tan(½ FoV) = max(W / 2f_x, H / 2f_y)`` (the wider half-angle). For
   NeRF-synthetic (radius 4.03, FoV 0.69 rad) this is ±1.45, close to the ±1.3 of 3DGS. When it is 0
   (the cameras sit at ``x``) the camera extent is used.
3. **Points** (``data.random_init``), from ``numpy.random.default_rng(seed)`` (deterministic); colours
   mid-grey (128, 128, 128) uint8:

   - ``cube``: ``num`` (default 100 000) uniform in the cube ``x ± h``. That is what the cameras of an
     object-centric capture (NeRF-synthetic) look at, but a room-scale capture's walls, floor and
     ceiling lie outside it: the training views are then fitted by floaters inside the cube, which the
     held-out views expose (``experiments/README.md``).
   - ``cube_and_rays``: half the points in the cube as above, the other half along the training
     cameras' rays — a uniform camera, a uniform pixel, a depth (along the optical axis) uniform in
     ``[½ D, 2½ D]`` with ``D = median_i ‖x − C_i‖`` the distance the cameras look at — so that
     whatever lies up to about two and a half times that far in any training view has points near it
     (the demo room's walls lie at 0.4–2.1 D).

   - ``auto`` (the default): ``cube`` for Blender scenes, which are object-centric (NeRF-synthetic, where
     3DGS and Scaffold-GS use the cube), ``cube_and_rays`` for nerfstudio scenes without a PLY, which are
     real captures with walls or a background around the cameras (:func:`resolve_random_init`).

   Only the training cameras are used (never the held-out ones), for the cube as for the rays.
   ``auto`` keeps the cube on Blender scenes because it is the published NeRF-synthetic protocol, not
   because it scored higher (the two rules' scores: ``experiments/README.md``, ``random_init_rays.sh``).

**Voxel size.** ``model.voxel_size=auto`` is *not* the median nearest-neighbour spacing of these points
(:func:`cusgs_jax.model.anchors.auto_voxel_size`, the rule for SfM points): for N uniform points in a cube
of side 2h that spacing is ``2h·(3 ln 2 / 4πN)^{1/3}`` — it says how many points were drawn, not how
fine the scene is (0.0151 × the extent for 10 000 points on the demo objects of
:mod:`cusgs_jax.data.demo.objects`, 6.6 × the 0.0023 that their SfM points give). Instead
(:func:`random_voxel_size`, used when ``SceneData.random_points`` is set): **half a pixel's footprint at
the distance the cameras look at**, ``0.5 × median_i ‖x − C_i‖ / median_i f_i`` (``x`` the centre above,
``f_i = max(fx, fy)`` in pixels). On the demo objects (128 px, distance 4.5, FoV 0.69) it is 0.0127 m =
0.0023 × the extent — the SfM points' spacing; on NeRF-synthetic at 800 px, 0.0018 (Scaffold-GS uses
0.001 there). Nearly every random point then becomes an anchor (Scaffold-GS's one anchor per point); the
anchors in empty space are pruned by the growing schedule within the first ~500 steps. Against the
spacing rule on the demo objects: ``experiments/README.md`` (``random_init_objects.py``).
"""

from __future__ import annotations

import numpy as np

from cusgs_jax.config import RANDOM_POINT_RULES, DataConfig
from cusgs_jax.data.normalize import camera_centers, camera_extent

__all__ = ["GREY", "random_box", "random_points", "random_voxel_size", "ray_points",
           "resolve_random_init"]

GREY = 128
RAY_DEPTHS = (0.5, 2.5)  # the rays' depth range, in units of the distance the cameras look at
_MIN_SPREAD = 0.02  # smallest eigenvalue of Σ(I − d dᵀ) / V for the axes' nearest point to be trusted


def _axes(viewmats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(camera centres [V, 3], unit viewing directions [V, 3]) of world→camera ``viewmats`` [V, 4, 4] (OpenCV)."""
    dirs = np.asarray(viewmats, np.float64)[:, 2, :3]  # the camera's +z axis in world coordinates
    return camera_centers(viewmats), dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)


def _look_distance(viewmats: np.ndarray, center: np.ndarray) -> float:
    """``D = median_i ‖x − C_i‖``: the distance the cameras look at, from the centre ``x`` [3] of
    :func:`random_box` (it sizes the cube, the voxel and the rays' depths)."""
    return float(np.median(np.linalg.norm(center - camera_centers(viewmats), axis=-1)))


def random_box(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int) -> tuple[np.ndarray, float]:
    """(centre [3] float64, half-side h > 0) of the cube the cameras look at (the module's rule).

    Args:
      viewmats: [V, 4, 4] world→camera (OpenCV axes); Ks: [V, 3, 3] intrinsics at ``width`` × ``height``.
    """
    centers, dirs = _axes(viewmats)
    Ks = np.asarray(Ks, np.float64)
    views = len(centers)
    extent, mean = camera_extent(centers, np.zeros((0, 3)))
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [V, 3, 3] I − d dᵀ
    a = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, centers)
    center = None
    if np.linalg.eigvalsh(a)[0] >= _MIN_SPREAD * views:
        candidate = np.linalg.solve(a, b)
        if np.median(np.einsum("ni,ni->n", candidate - centers, dirs)) > 0:
            center = candidate
    if center is None:
        forward = dirs.mean(axis=0)
        norm = np.linalg.norm(forward)
        center = mean + (forward / norm * extent if norm > 1e-6 else 0.0)
    tan_half = np.maximum(0.5 * width / Ks[:, 0, 0], 0.5 * height / Ks[:, 1, 1])
    half = float(_look_distance(viewmats, center) * np.median(tan_half))
    if not (np.isfinite(half) and half > 0):
        half = float(extent)
    return np.asarray(center, np.float64), half


def random_voxel_size(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int) -> float:
    """``model.voxel_size=auto`` for random points: half a pixel's footprint at the distance the cameras
    look at, ``0.5 × median_i ‖x − C_i‖ / median_i f_i`` (``x`` the centre of :func:`random_box`, ``C_i`` the
    camera centres, ``f_i = max(fx, fy)``), in the units of ``viewmats`` (module docstring).

    Args:
      viewmats: [V, 4, 4] world→camera (OpenCV axes); Ks: [V, 3, 3] at ``width`` × ``height``.
    """
    center, half = random_box(viewmats, Ks, width, height)
    Ks = np.asarray(Ks, np.float64)
    focal = np.maximum(Ks[:, 0, 0], Ks[:, 1, 1])
    size = float(0.5 * _look_distance(viewmats, center) / np.median(focal))
    if not (np.isfinite(size) and size > 0):  # the cameras sit at x: a 1/1000 of the cube
        size = 1e-3 * 2 * half
    return size


_AUTO_RULE = {"blender": "cube", "nerfstudio": "cube_and_rays"}


def resolve_random_init(init: str, dataset_format: str) -> str:
    """The rule ``data.random_init`` stands for in a scene of layout ``dataset_format``: itself, or for
    ``"auto"`` ``cube`` (Blender) / ``cube_and_rays`` (nerfstudio and anything else) — the module docstring."""
    if init != "auto":
        return init
    return _AUTO_RULE.get(dataset_format, "cube_and_rays")


def ray_points(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int, num: int,
               rng: np.random.Generator) -> np.ndarray:
    """``num`` points along random rays of the cameras (the ``cube_and_rays`` rule of the module docstring).

    Each point takes a uniform camera, a uniform position in its ``width`` × ``height`` image and a depth
    along its optical axis uniform in ``RAY_DEPTHS`` × ``D`` (``D`` the median distance from the camera
    centres to the centre of :func:`random_box`).

    Args:
      viewmats: [V, 4, 4] world→camera (OpenCV axes); Ks: [V, 3, 3] pinhole intrinsics; rng: the generator.
    Returns:
      points [num, 3] float64 in the frame of ``viewmats``; each lies in front of the camera it was drawn
      for and projects inside its image.
    """
    viewmats = np.asarray(viewmats, np.float64)
    Ks = np.asarray(Ks, np.float64)
    center, half = random_box(viewmats, Ks, width, height)
    distance = _look_distance(viewmats, center)
    if not (np.isfinite(distance) and distance > 0):  # the cameras sit at x: the cube's size instead
        distance = 2.0 * half
    view = rng.integers(len(viewmats), size=num)
    pixel = rng.uniform((0.0, 0.0), (float(width), float(height)), size=(num, 2))
    depth = rng.uniform(RAY_DEPTHS[0] * distance, RAY_DEPTHS[1] * distance, size=num)
    K = Ks[view]
    camera = np.stack([(pixel[:, 0] - K[:, 0, 2]) / K[:, 0, 0], (pixel[:, 1] - K[:, 1, 2]) / K[:, 1, 1],
                       np.ones(num)], axis=-1) * depth[:, None]  # [num, 3] in camera coordinates
    rotation, translation = viewmats[view, :3, :3], viewmats[view, :3, 3]
    return np.einsum("nji,nj->ni", rotation, camera - translation)  # Rᵀ (p − t)


def random_points(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int, *,
                  num: int = DataConfig.random_points, seed: int = 0, init: str = "cube") -> tuple[np.ndarray, np.ndarray]:
    """``num`` random initial points for the training cameras ``viewmats``, ``Ks`` by the rule ``init``.

    Args:
      viewmats: [V, 4, 4] world→camera of the *training* views; Ks: [V, 3, 3] at ``width`` × ``height``.
      init: ``"cube"`` (uniform in :func:`random_box`) or ``"cube_and_rays"`` (half of them there, half
        :func:`ray_points`), the module docstring's rules (``data.random_init``).
    Returns:
      (points [num, 3] float64, colours [num, 3] uint8, all mid-grey); the same for the same
      cameras, ``num``, ``seed`` and ``init``.
    """
    if init not in RANDOM_POINT_RULES:
        raise ValueError(f"init={init!r} must be one of {RANDOM_POINT_RULES} (resolve 'auto' first)")
    num = int(num)
    center, half = random_box(viewmats, Ks, width, height)
    rng = np.random.default_rng(seed)
    on_rays = num // 2 if init == "cube_and_rays" else 0
    points = center + rng.uniform(-half, half, size=(num - on_rays, 3))
    if on_rays:
        points = np.concatenate([points, ray_points(viewmats, Ks, width, height, on_rays, rng)])
    return points, np.full((num, 3), GREY, np.uint8)
