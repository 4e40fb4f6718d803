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
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["generate_demo_scene", "demo_scene_path", "main"]

FORMAT_VERSION = 3  # 2: SfM points sampled from observed pixels; 3: cameras never see the ceiling
FOCAL_FACTOR = 0.8  # fx = fy = FOCAL_FACTOR * width (horizontal FOV ~64 deg)
_TEXTURE_MAX_SIDE = 768
_EPS = 1e-9
# An observation of a sampled point is kept only if the depth map (pixel-centre ray) at the pixel
# it projects into agrees with the point's depth to this relative tolerance. Occlusion itself is
# decided exactly by ray casting; this only drops observations whose pixel centre sees another
# surface (occlusion edges) or sees the same surface at an extreme grazing angle.
_OBS_DEPTH_RTOL = 1e-2


# ---------------------------------------------------------------------------------------------
# Scene description
# ---------------------------------------------------------------------------------------------

# name, texture, tint (grayscale textures are tinted), boxes [(lo, hi)], inside-out
_OBJECTS = [
    ("floor", "brick", (0.95, 0.62, 0.42), [((-3, -3, 0), (3, 3, 0))], False),
    ("ceiling", "moon", (0.85, 0.9, 1.0), [((-3, -3, 3), (3, 3, 3))], False),
    ("wall_north", "astronaut", None, [((-3, 3, 0), (3, 3, 3))], False),
    ("wall_south", "rocket", None, [((-3, -3, 0), (3, -3, 3))], False),
    ("wall_east", "hubble_deep_field", None, [((3, -3, 0), (3, 3, 3))], False),
    ("wall_west", "stereo_motorcycle", None, [((-3, -3, 0), (-3, 3, 3))], False),
    ("table_top", "coffee", None, [((-0.7, -0.45, 0.72), (0.7, 0.45, 0.78))], False),
    ("table_legs", "gravel", (0.7, 0.5, 0.35), [
        ((sx * 0.62 - 0.03, sy * 0.37 - 0.03, 0.0), (sx * 0.62 + 0.03, sy * 0.37 + 0.03, 0.72))
        for sx in (-1, 1) for sy in (-1, 1)], False),
    ("box_cat", "chelsea", None, [((-0.55, -0.30, 0.78), (-0.20, 0.05, 1.08))], False),
    ("box_tall", "colorwheel", None, [((0.05, 0.05, 0.78), (0.30, 0.30, 1.23))], False),
    ("box_flat", "immunohistochemistry", None, [((0.25, -0.35, 0.78), (0.60, -0.12, 0.93))], False),
    ("box_floor", "coins", (1.0, 0.8, 0.35), [((0.90, 0.60, 0.0), (1.30, 1.00, 0.40))], False),
    ("chair", "camera", (0.55, 0.75, 1.0), [
        ((-1.35, -0.22, 0.42), (-0.90, 0.22, 0.47)),  # seat
        ((-1.35, -0.22, 0.47), (-1.30, 0.22, 1.00)),  # backrest
    ] + [((x, y, 0.0), (x + 0.04, y + 0.04, 0.42)) for x in (-1.35, -0.94) for y in (-0.22, 0.18)],
        False),
    ("cabinet", "retina", None, [((2.55, -1.0, 0.0), (3.0, 0.0, 1.10))], False),
    ("box_on_cabinet", "logo", None, [((2.62, -0.80, 1.10), (2.92, -0.45, 1.36))], False),
    ("shelf", "page", (1.0, 0.88, 0.7), [((-1.5, 2.6, 0.0), (0.2, 3.0, 1.8))], False),
    ("bench", "grass", (0.55, 0.95, 0.45), [((-0.8, -2.9, 0.0), (0.8, -2.5, 0.45))], False),
]
# The room itself is one inside-out box; its six faces belong to the first six objects.
_ROOM = ((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0))
_ROOM_FACE_OBJECTS = {  # (axis, side) -> object name; side 0 = lo plane, 1 = hi plane
    (2, 0): "floor", (2, 1): "ceiling", (1, 1): "wall_north", (1, 0): "wall_south",
    (0, 1): "wall_east", (0, 0): "wall_west",
}
_TABLE_CENTRE = np.array([0.0, 0.0, 0.85])


def _load_texture(name, tint):
    """A scikit-image sample photo (shipped with the package, no download) as uint8 [h, w, 3]."""
    import skimage.data

    img = getattr(skimage.data, name)()
    if isinstance(img, tuple):  # stereo_motorcycle -> (left, right, disparity)
        img = img[0]
    img = np.asarray(img)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 3 and img.shape[-1] == 4:
        img = img[..., :3]
    img = img.astype(np.float64) / (255.0 if img.dtype == np.uint8 else max(float(img.max()), 1e-9))
    if img.ndim == 2:
        tint = np.asarray(tint if tint is not None else (1.0, 1.0, 1.0), np.float64)
        img = 0.12 + 0.88 * img[..., None] * tint
    h, w = img.shape[:2]
    f = -(-max(h, w) // _TEXTURE_MAX_SIDE)  # integer box-filter downsampling of huge photos
    if f > 1:
        img = img[:h - h % f, :w - w % f].reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


@dataclass
class _Scene:
    """Flattened scene: boxes, their faces, and a texture atlas.

    Faces are indexed ``6 * box + 2 * axis + side`` (side 0 = the box's lo plane, 1 = hi plane).
    Each face is parametrised as ``p(u, v) = origin + u * e1 + v * e2`` with (u, v) in [0, 1]^2;
    (u, v) are also the texture coordinates (u -> texture column, v -> texture row), oriented so
    that the image appears upright and unmirrored to a viewer in front of the face.
    """

    box_lo: np.ndarray  # [B, 3]
    box_hi: np.ndarray  # [B, 3]
    box_inside: np.ndarray  # [B] bool: inside-out box (the room)
    face_origin: np.ndarray  # [F, 3]
    face_e1: np.ndarray  # [F, 3]
    face_e2: np.ndarray  # [F, 3]
    face_obj: np.ndarray  # [F] object id (1-based)
    face_tex: np.ndarray  # [F] texture index into the atlas
    face_shade: np.ndarray  # [F] fixed Lambertian shading factor
    face_area: np.ndarray  # [F]
    atlas: np.ndarray  # [T, Hmax, Wmax, 3] uint8
    atlas_hw: np.ndarray  # [T, 2] texture sizes
    objects: list  # [{"id", "name", "texture", "boxes"}]


def _shade(normal):
    """Fixed per-face shading from the (viewer-facing) face normal: a soft top-down light."""
    table = {(2, 1): 1.0, (2, -1): 0.62, (0, 1): 0.9, (0, -1): 0.78, (1, 1): 0.84, (1, -1): 0.72}
    a = int(np.argmax(np.abs(normal)))
    return table[(a, int(np.sign(normal[a])))]


@lru_cache(maxsize=1)
def _build_scene():
    names = [o[0] for o in _OBJECTS]
    textures = [o[1] for o in _OBJECTS]
    assert len(set(textures)) == len(textures), "every object must use a different photo"
    tex_imgs = [_load_texture(o[1], o[2]) for o in _OBJECTS]
    hmax = max(t.shape[0] for t in tex_imgs)
    wmax = max(t.shape[1] for t in tex_imgs)
    atlas = np.zeros((len(tex_imgs), hmax, wmax, 3), np.uint8)
    for k, t in enumerate(tex_imgs):
        atlas[k, :t.shape[0], :t.shape[1]] = t
    atlas_hw = np.array([t.shape[:2] for t in tex_imgs], np.int64)

    # Boxes: the room (inside-out) first, then every solid object box. The flat rectangles listed
    # for floor/ceiling/walls in _OBJECTS only document those objects; the room box renders them.
    boxes = [(_ROOM[0], _ROOM[1], True, None)]
    for k, (name, _, _, bxs, _) in enumerate(_OBJECTS):
        if name in _ROOM_FACE_OBJECTS.values():
            continue
        for lo, hi in bxs:
            boxes.append((lo, hi, False, k))
    origin, e1, e2, obj, tex, shade, area = [], [], [], [], [], [], []
    ez = np.array([0.0, 0.0, 1.0])
    for lo, hi, inside, k in boxes:
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        size = hi - lo
        for axis in range(3):
            for side in range(2):
                if inside:
                    k_face = names.index(_ROOM_FACE_OBJECTS[(axis, side)])
                else:
                    k_face = k
                # Viewer-facing normal: outward for solid boxes, inward for the room.
                n = np.zeros(3)
                n[axis] = (1.0 if side == 1 else -1.0) * (-1.0 if inside else 1.0)
                o = lo.copy()
                o[axis] = hi[axis] if side == 1 else lo[axis]
                if axis == 2:  # horizontal face: u along x, v along y
                    a1 = np.array([size[0], 0, 0])
                    a2 = np.array([0, size[1], 0])
                else:  # vertical face: u along the viewer's right, v downwards
                    right = np.cross(-n, ez)
                    h = int(np.argmax(np.abs(right)))
                    a1 = np.zeros(3)
                    a1[h] = size[h] * np.sign(right[h])
                    if right[h] < 0:
                        o[h] = hi[h]
                    o[2] = hi[2]
                    a2 = np.array([0, 0, -size[2]])
                origin.append(o)
                e1.append(a1)
                e2.append(a2)
                obj.append(k_face + 1)
                tex.append(k_face)
                shade.append(_shade(n))
                area.append(np.linalg.norm(a1) * np.linalg.norm(a2))
    objects = [
        {"id": k + 1, "name": o[0], "texture": o[1],
         "boxes": [[list(map(float, lo)), list(map(float, hi))] for lo, hi in o[3]]}
        for k, o in enumerate(_OBJECTS)
    ]
    return _Scene(
        box_lo=np.array([b[0] for b in boxes], np.float64),
        box_hi=np.array([b[1] for b in boxes], np.float64),
        box_inside=np.array([b[2] for b in boxes]),
        face_origin=np.array(origin), face_e1=np.array(e1), face_e2=np.array(e2),
        face_obj=np.array(obj, np.int64), face_tex=np.array(tex, np.int64),
        face_shade=np.array(shade, np.float64), face_area=np.array(area, np.float64),
        atlas=atlas, atlas_hw=atlas_hw, objects=objects,
    )


# ---------------------------------------------------------------------------------------------
# Ray casting and texturing
# ---------------------------------------------------------------------------------------------

def _cast(scene, origin, dirs):
    """Nearest intersection of rays ``origin + t * dirs`` (t > 0) with the scene.

    Args:
      origin: [3] ray origin (a camera centre).
      dirs: [N, 3] ray directions (not necessarily normalised).
    Returns:
      t [N] float64 (inf where nothing is hit) and face [N] int64 (-1 where nothing is hit).
    """
    n = dirs.shape[0]
    d = [np.ascontiguousarray(dirs[:, a]) for a in range(3)]
    with np.errstate(divide="ignore"):
        inv = [1.0 / np.where(c == 0.0, 1e-300, c) for c in d]
    pos = [c > 0.0 for c in d]
    best_t = np.full(n, np.inf)
    best_face = np.full(n, -1, np.int64)
    for b in range(scene.box_lo.shape[0]):
        lo, hi = scene.box_lo[b], scene.box_hi[b]
        tn, tf = [], []  # per-axis entry / exit parameters
        for a in range(3):
            t1 = (lo[a] - origin[a]) * inv[a]
            t2 = (hi[a] - origin[a]) * inv[a]
            tn.append(np.where(pos[a], t1, t2))
            tf.append(np.where(pos[a], t2, t1))
        face0 = 6 * b
        if scene.box_inside[b]:
            # Leave the (inside-out) room through the nearest exit plane: moving towards +axis
            # exits through the hi plane (side 1).
            t = np.minimum(np.minimum(tf[0], tf[1]), tf[2])
            face = np.where(t == tf[0], face0 + pos[0],
                            np.where(t == tf[1], face0 + 2 + pos[1], face0 + 4 + pos[2]))
            hit = t > _EPS
        else:
            # Enter a solid box through the last entry plane: moving towards -axis enters
            # through the hi plane (side 1).
            t = np.maximum(np.maximum(tn[0], tn[1]), tn[2])
            face = np.where(t == tn[0], face0 + ~pos[0],
                            np.where(t == tn[1], face0 + 2 + ~pos[1], face0 + 4 + ~pos[2]))
            hit = (t > _EPS) & (t <= np.minimum(np.minimum(tf[0], tf[1]), tf[2]))
        better = hit & (t < best_t)
        best_t = np.where(better, t, best_t)
        best_face = np.where(better, face, best_face)
    return best_t, best_face


def _face_uv(scene, points, face):
    """Texture coordinates (u, v) in [0, 1] of points [N, 3] lying on faces [N]."""
    d = points - scene.face_origin[face]
    e1 = scene.face_e1[face]
    e2 = scene.face_e2[face]
    u = np.einsum("ij,ij->i", d, e1) / np.einsum("ij,ij->i", e1, e1)
    v = np.einsum("ij,ij->i", d, e2) / np.einsum("ij,ij->i", e2, e2)
    return np.clip(u, 0.0, 1.0), np.clip(v, 0.0, 1.0)


def _surface_colour(scene, points, face):
    """Shaded Lambertian colour (float64 RGB in [0, 1], [N, 3]) of points on faces (>= 0)."""
    u, v = _face_uv(scene, points, face)
    tex = scene.face_tex[face]
    hw = scene.atlas_hw[tex]
    # Bilinear lookup, texel centres at integer + 0.5 (the texture is stretched once over the face).
    x = np.clip(u * hw[:, 1] - 0.5, 0.0, hw[:, 1] - 1.0)
    y = np.clip(v * hw[:, 0] - 0.5, 0.0, hw[:, 0] - 1.0)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, hw[:, 1] - 1)
    y1 = np.minimum(y0 + 1, hw[:, 0] - 1)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    a = scene.atlas
    c = ((a[tex, y0, x0] * (1 - fx) + a[tex, y0, x1] * fx) * (1 - fy)
         + (a[tex, y1, x0] * (1 - fx) + a[tex, y1, x1] * fx) * fy) / 255.0
    return c * scene.face_shade[face][:, None]


def _camera_rays(R, width, height, K, offsets):
    """World-space ray directions with camera-space z = 1 (so the ray parameter t is the depth).

    Returns [len(offsets), H*W, 3] for sub-pixel offsets (dx, dy) within each pixel.
    """
    fx, fy, cx, cy = K
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    out = []
    for dx, dy in offsets:
        d_cam = np.stack([(jj + dx - cx) / fx, (ii + dy - cy) / fy, np.ones_like(jj)], -1)
        out.append(d_cam.reshape(-1, 3) @ R)  # R^T d  (row-vector form)
    return np.stack(out)


def _render_view(scene, R, t, width, height, K, supersample=True):
    """Ray-cast one view.

    Returns:
      image uint8 [H, W, 3], depth float32 [H, W] (camera z, 0 = none),
      object ids uint8 [H, W] (0 = none), face ids int64 [H, W] (-1 = none).
    """
    centre = -R.T @ t
    (d_c,) = _camera_rays(R, width, height, K, [(0.5, 0.5)])
    tc, fc = _cast(scene, centre, d_c)
    hit = fc >= 0
    depth = np.where(hit, tc, 0.0).astype(np.float32).reshape(height, width)
    obj = np.where(hit, scene.face_obj[np.maximum(fc, 0)], 0).astype(np.uint8)
    if supersample:  # 2x2 supersampling of the colour only
        dirs = _camera_rays(R, width, height, K,
                            [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)])
    else:
        dirs = d_c[None]
    colour = np.zeros((width * height, 3))
    for d in dirs:
        ts, fs = _cast(scene, centre, d)
        ok = fs >= 0
        colour[ok] += _surface_colour(scene, centre + ts[ok, None] * d[ok], fs[ok])
    colour /= dirs.shape[0]
    image = np.round(np.clip(colour, 0.0, 1.0) * 255.0).astype(np.uint8).reshape(height, width, 3)
    return image, depth, obj.reshape(height, width), fc.reshape(height, width)


# ---------------------------------------------------------------------------------------------
# Cameras and points
# ---------------------------------------------------------------------------------------------

def _look_at(centre, target, roll):
    """World->camera rotation (OpenCV: x right, y down, z forward) looking from centre at target."""
    f = target - centre
    f /= np.linalg.norm(f)
    x = np.cross(f, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])  # rows: camera axes in world coordinates
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ R


def _make_cameras(scene, num_views, seed):
    """Orbit around the table at smoothly varying radius and height; returns [(R, t), ...]."""
    rng = np.random.default_rng([seed, 0])
    phase = rng.uniform(0, 2 * np.pi, 3)
    poses = []
    for k in range(num_views):
        a = 2 * np.pi * k / num_views
        ang = a + phase[0] + rng.normal(0, 0.25 * np.pi / num_views)
        radius = 2.05 + 0.25 * np.sin(2 * a + phase[1]) + rng.uniform(-0.03, 0.03)
        # 1.4–1.9: always looking down enough that no view sees the ceiling,
        # which no other view would cover (a held-out view would then be
        # judged on unobserved content)
        height = 1.65 + 0.25 * np.sin(3 * a + phase[2]) + rng.uniform(-0.05, 0.05)
        centre = np.array([radius * np.cos(ang), radius * np.sin(ang), height])
        inside = np.all((centre > scene.box_lo[1:] - 0.05) & (centre < scene.box_hi[1:] + 0.05),
                        axis=1)
        if inside.any():  # cannot happen with the fixed layout; keep generation honest anyway
            raise RuntimeError(f"camera {k} at {centre} is inside an object")
        target = _TABLE_CENTRE + rng.normal(0, [0.12, 0.12, 0.06])
        R = _look_at(centre, target, rng.normal(0, np.deg2rad(2.0)))
        poses.append((R, -R @ centre))
    return poses


def _sample_points(poses, K, depths, face_maps, num_points, seed):
    """Surface points where the cameras look, like an SfM point cloud.

    Draws ``num_points`` (view, pixel) pairs uniformly among the pixels that
    show a surface and back-projects each pixel centre with its depth, so every
    surface gets points in proportion to how much it is seen (a surface seen
    only at image edges still gets some), and every point lies exactly on the
    face it came from.

    Returns:
      (xyz [N, 3], face [N]).
    """
    rng = np.random.default_rng([seed, 1])
    fx, fy, cx, cy = K
    faces = np.stack(face_maps)  # [V, H, W]
    candidates = np.flatnonzero(faces.reshape(-1) >= 0)
    pick = rng.choice(candidates, size=min(num_points, len(candidates)), replace=False)
    view, rest = np.divmod(pick, faces.shape[1] * faces.shape[2])
    row, col = np.divmod(rest, faces.shape[2])
    z = np.stack(depths)[view, row, col].astype(np.float64)
    cam = np.stack([(col + 0.5 - cx) / fx * z, (row + 0.5 - cy) / fy * z, z], axis=-1)
    xyz = np.empty_like(cam)
    for v in np.unique(view):
        R, t = poses[v]
        sel = view == v
        xyz[sel] = (cam[sel] - t) @ R  # R^T (p_c - t)
    return xyz, faces[view, row, col]


def _observe(scene, xyz, face, poses, K, width, height, depths, face_maps):
    """Which views see which points, and where.

    A point is observed in a view when it projects inside the image, the first surface along the
    camera ray towards it is the point itself (exact ray cast), and the centre ray of the pixel
    it falls in hits the same face at nearly the same depth (relative _OBS_DEPTH_RTOL), so every
    keypoint is consistent with the depth and object-id maps at its pixel.
    Returns visible [V, N] bool and pixel coordinates xy [V, N, 2] (COLMAP convention).
    """
    fx, fy, cx, cy = K
    V, N = len(poses), xyz.shape[0]
    visible = np.zeros((V, N), bool)
    xy = np.zeros((V, N, 2))
    for v, (R, t) in enumerate(poses):
        pc = xyz @ R.T + t
        z = pc[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        u = fx * pc[:, 0] / zs + cx
        w = fy * pc[:, 1] / zs + cy
        xy[v, :, 0], xy[v, :, 1] = u, w
        inimg = front & (u >= 0) & (u < width) & (w >= 0) & (w < height)
        idx = np.flatnonzero(inimg)
        if idx.size == 0:
            continue
        centre = -R.T @ t
        d = (xyz[idx] - centre) / z[idx, None]  # camera z = 1 -> t equals the depth
        th, fh = _cast(scene, centre, d)
        ok = (fh == face[idx]) & (np.abs(th - z[idx]) <= 1e-6 * z[idx])
        col = np.clip(np.floor(u[idx]).astype(np.int64), 0, width - 1)
        row = np.clip(np.floor(w[idx]).astype(np.int64), 0, height - 1)
        ok &= face_maps[v][row, col] == face[idx]
        dm = depths[v][row, col].astype(np.float64)
        ok &= np.abs(dm - z[idx]) <= _OBS_DEPTH_RTOL * z[idx]
        visible[v, idx[ok]] = True
    return visible, xy


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------

def _write_colmap(sparse_dir, poses, K, width, height, names, xyz, colours, visible, xy):
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=width, height=height,
                          params=[float(k) for k in K], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    # point2D index of point p in view v (points are listed in increasing point order).
    obs_idx = np.cumsum(visible, axis=1) - 1
    for v, (R, t) in enumerate(poses):
        kp = xy[v, visible[v]]
        img = pycolmap.Image(name=names[v], keypoints=np.ascontiguousarray(kp, np.float64),
                             camera_id=1, image_id=v + 1)
        pose = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(np.ascontiguousarray(R)),
                                translation=np.asarray(t, np.float64))
        rec.add_image_with_trivial_frame(img, pose)
    for p in range(xyz.shape[0]):
        track = pycolmap.Track()
        for v in np.flatnonzero(visible[:, p]):
            track.add_element(int(v + 1), int(obs_idx[v, p]))
        rec.add_point3D(xyz[p], track, colours[p])  # also links the images' points2D
    if hasattr(rec, "update_point_3d_errors"):
        rec.update_point_3d_errors()
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(sparse_dir))
    return rec


_OUTPUTS = ("images", "sparse", "depth", "object_ids", "objects.json", "scene.json")


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
    import imageio.v3 as iio

    if num_views < 2 or width < 2 or height < 2 or num_points < 1:
        raise ValueError("need num_views >= 2, width/height >= 2 and num_points >= 1")
    out = pathlib.Path(out_dir)
    existing = [e for e in _OUTPUTS if (out / e).exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{out} already contains a scene ({', '.join(existing)}); "
                              "pass overwrite=True to replace it")
    for e in existing:
        shutil.rmtree(out / e) if (out / e).is_dir() else (out / e).unlink()

    t0 = time.perf_counter()
    scene = _build_scene()
    K = (FOCAL_FACTOR * width, FOCAL_FACTOR * width, width / 2.0, height / 2.0)
    poses = _make_cameras(scene, num_views, seed)
    names = [f"view_{v:03d}.png" for v in range(num_views)]
    for sub in ("images", "depth", "object_ids"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    depths, face_maps = [], []
    for v, (R, t) in enumerate(poses):
        image, depth, obj, faces = _render_view(scene, R, t, width, height, K)
        stem = names[v][:-4]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            iio.imwrite(out / "images" / names[v], image)
        np.save(out / "depth" / f"{stem}.npy", depth)
        np.save(out / "object_ids" / f"{stem}.npy", obj)
        depths.append(depth)
        face_maps.append(faces)

    xyz, face = _sample_points(poses, K, depths, face_maps, num_points, seed)
    visible, xy = _observe(scene, xyz, face, poses, K, width, height, depths, face_maps)
    keep = visible.sum(axis=0) >= 2
    xyz, face, visible, xy = xyz[keep], face[keep], visible[:, keep], xy[:, keep]
    colours = np.round(np.clip(_surface_colour(scene, xyz, face), 0, 1) * 255).astype(np.uint8)
    _write_colmap(out / "sparse" / "0", poses, K, width, height, names, xyz, colours, visible, xy)

    (out / "objects.json").write_text(json.dumps(scene.objects, indent=1) + "\n")
    track_len = visible.sum(axis=0)
    info = {
        "generator": "cusgs_jax.data.demo", "format_version": FORMAT_VERSION,
        "seed": seed, "num_views": num_views, "width": width, "height": height,
        "num_points_sampled": num_points, "num_points": int(xyz.shape[0]),
        "mean_track_length": float(track_len.mean()) if track_len.size else 0.0,
        "camera_model": "PINHOLE", "intrinsics": {"fx": K[0], "fy": K[1], "cx": K[2], "cy": K[3]},
        "world_up": [0.0, 0.0, 1.0], "room_bounds": [list(_ROOM[0]), list(_ROOM[1])],
        "look_at": _TABLE_CENTRE.tolist(), "images": names,
        "generation_seconds": round(time.perf_counter() - t0, 3),
    }
    (out / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    return out


def _default_cache_dir():
    env = os.environ.get("CUSGS_CACHE_DIR")
    return pathlib.Path(env) if env else pathlib.Path.home() / ".cache" / "cusgs_jax"


def demo_scene_path(cache_dir=None, *, seed=0, num_views=30, width=160, height=120) -> pathlib.Path:
    """Folder of the demo scene for these parameters, generating it on first use.

    The scene lives in ``cache_dir`` (default ``$CUSGS_CACHE_DIR`` or ``~/.cache/cusgs_jax``)
    under ``demo{FORMAT_VERSION}-s{seed}-v{num_views}-{width}x{height}``. It is generated into a temporary
    sibling folder and renamed into place, so an interrupted generation never leaves a partial
    scene behind; an existing complete folder is reused as is.
    """
    root = pathlib.Path(cache_dir) if cache_dir is not None else _default_cache_dir()
    name = f"demo{FORMAT_VERSION}-s{seed}-v{num_views}-{width}x{height}"
    final = root / name
    if (final / "scene.json").is_file():
        return final
    root.mkdir(parents=True, exist_ok=True)
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
        generate_demo_scene(tmp, seed=seed, num_views=num_views, width=width, height=height,
                            overwrite=True)
        try:
            os.replace(tmp, final)
        except OSError:
            if not (final / "scene.json").is_file():  # lost a race only if the winner finished
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def main(argv=None):
    """CLI: ``cusgs-demo-scene OUT [--views 30 --width 160 --height 120 --seed 0 --overwrite]``."""
    ap = argparse.ArgumentParser(prog="cusgs-demo-scene",
                                 description="Generate the synthetic demo room as a COLMAP scene.")
    ap.add_argument("out", help="output folder")
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--points", type=int, default=6000, help="surface samples (before filtering)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    try:
        out = generate_demo_scene(args.out, seed=args.seed, num_views=args.views,
                                  width=args.width, height=args.height, num_points=args.points,
                                  overwrite=args.overwrite)
    except (FileExistsError, ValueError) as e:
        ap.exit(1, f"cusgs-demo-scene: error: {e}\n")
    info = json.loads((out / "scene.json").read_text())
    print(f"demo scene -> {out}\n"
          f"  {info['num_views']} views {info['width']}x{info['height']} (PINHOLE fx=fy="
          f"{info['intrinsics']['fx']:g}), {len(_OBJECTS)} objects\n"
          f"  {info['num_points']} points (of {info['num_points_sampled']} sampled), mean track "
          f"length {info['mean_track_length']:.2f}\n"
          f"  generated in {time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
