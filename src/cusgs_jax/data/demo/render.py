"""Geometry, textures, ray casting and cameras of the demo room (:mod:`cusgs_jax.data.demo`).

The room is fixed: a closed box (floor, four walls, ceiling, seen from inside) furnished with
axis-aligned boxes, each object textured with a different scikit-image sample photo stretched
once over each face, Lambertian with a fixed per-face shading factor. Everything is NumPy,
float64, deterministic; the world frame is z up, cameras are OpenCV world->camera ``(R, t)``
with intrinsics ``K = (fx, fy, cx, cy)`` (conventions: :mod:`cusgs_jax.data.demo`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = [
    "ROOM",
    "TABLE_CENTRE",
    "DemoScene",
    "build_scene",
    "cast_rays",
    "make_cameras",
    "render_view",
    "surface_colour",
]

_TEXTURE_MAX_SIDE = 768
_EPS = 1e-9


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
ROOM = ((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0))
_ROOM_FACE_OBJECTS = {  # (axis, side) -> object name; side 0 = lo plane, 1 = hi plane
    (2, 0): "floor", (2, 1): "ceiling", (1, 1): "wall_north", (1, 0): "wall_south",
    (0, 1): "wall_east", (0, 0): "wall_west",
}
TABLE_CENTRE = np.array([0.0, 0.0, 0.85])


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
class DemoScene:
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


def _texture_atlas() -> tuple[np.ndarray, np.ndarray]:
    """The photos of every object (in _OBJECTS order) packed into one zero-padded atlas.

    Returns:
      atlas uint8 [T, Hmax, Wmax, 3] and atlas_hw int64 [T, 2] (each texture's height, width).
    """
    textures = [o[1] for o in _OBJECTS]
    assert len(set(textures)) == len(textures), "every object must use a different photo"
    tex_imgs = [_load_texture(o[1], o[2]) for o in _OBJECTS]
    hmax = max(t.shape[0] for t in tex_imgs)
    wmax = max(t.shape[1] for t in tex_imgs)
    atlas = np.zeros((len(tex_imgs), hmax, wmax, 3), np.uint8)
    for k, t in enumerate(tex_imgs):
        atlas[k, :t.shape[0], :t.shape[1]] = t
    atlas_hw = np.array([t.shape[:2] for t in tex_imgs], np.int64)
    return atlas, atlas_hw


def _scene_boxes() -> list[tuple]:
    """[(lo, hi, inside, object index or None), ...]: the room (inside-out) first, then every
    solid object box. The flat rectangles listed for floor/ceiling/walls in _OBJECTS only
    document those objects; the room box renders them."""
    boxes = [(ROOM[0], ROOM[1], True, None)]
    for k, (name, _, _, bxs, _) in enumerate(_OBJECTS):
        if name in _ROOM_FACE_OBJECTS.values():
            continue
        for lo, hi in bxs:
            boxes.append((lo, hi, False, k))
    return boxes


def _face_frame(lo: np.ndarray, hi: np.ndarray, axis: int, side: int, inside: bool):
    """One face of the box [lo, hi] ([3] float64 each): the plane ``axis`` at lo (side 0) or hi
    (side 1).

    Returns (n, origin, e1, e2), each [3] float64: the viewer-facing unit normal (outward for
    solid boxes, inward for the room) and the face parametrisation ``origin + u·e1 + v·e2``,
    (u, v) in [0, 1]^2 (see :class:`DemoScene`).
    """
    size = hi - lo
    n = np.zeros(3)
    n[axis] = (1.0 if side == 1 else -1.0) * (-1.0 if inside else 1.0)
    o = lo.copy()
    o[axis] = hi[axis] if side == 1 else lo[axis]
    if axis == 2:  # horizontal face: u along x, v along y
        a1 = np.array([size[0], 0, 0])
        a2 = np.array([0, size[1], 0])
    else:  # vertical face: u along the viewer's right, v downwards
        right = np.cross(-n, np.array([0.0, 0.0, 1.0]))
        h = int(np.argmax(np.abs(right)))
        a1 = np.zeros(3)
        a1[h] = size[h] * np.sign(right[h])
        if right[h] < 0:
            o[h] = hi[h]
        o[2] = hi[2]
        a2 = np.array([0, 0, -size[2]])
    return n, o, a1, a2


@lru_cache(maxsize=1)
def build_scene() -> DemoScene:
    """The demo room as a :class:`DemoScene` (built once per process, then cached)."""
    names = [o[0] for o in _OBJECTS]
    atlas, atlas_hw = _texture_atlas()
    boxes = _scene_boxes()
    origin, e1, e2, obj, tex, shade, area = [], [], [], [], [], [], []
    for lo, hi, inside, k in boxes:
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        for axis in range(3):
            for side in range(2):
                k_face = names.index(_ROOM_FACE_OBJECTS[(axis, side)]) if inside else k
                n, o, a1, a2 = _face_frame(lo, hi, axis, side, inside)
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
    return DemoScene(
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

def cast_rays(scene, origin, dirs):
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


def surface_colour(scene, points, face):
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


def camera_rays(R, width, height, K, offsets):
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


def mean_colour(scene, centre: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """[P, 3] surface colour seen from ``centre`` along the [K, P, 3] ray sets ``dirs`` (K sub-pixel
    samples of P pixels), averaged over the K samples; a ray that hits nothing adds black."""
    colour = np.zeros((dirs.shape[1], 3))
    for d in dirs:
        ts, fs = cast_rays(scene, centre, d)
        ok = fs >= 0
        colour[ok] += surface_colour(scene, centre + ts[ok, None] * d[ok], fs[ok])
    return colour / dirs.shape[0]


def render_view(scene, R, t, width, height, K, supersample=True):
    """Ray-cast one view.

    Returns:
      image uint8 [H, W, 3], depth float32 [H, W] (camera z, 0 = none),
      object ids uint8 [H, W] (0 = none), face ids int64 [H, W] (-1 = none).
    """
    centre = -R.T @ t
    (d_c,) = camera_rays(R, width, height, K, [(0.5, 0.5)])
    tc, fc = cast_rays(scene, centre, d_c)
    hit = fc >= 0
    depth = np.where(hit, tc, 0.0).astype(np.float32).reshape(height, width)
    obj = np.where(hit, scene.face_obj[np.maximum(fc, 0)], 0).astype(np.uint8)
    if supersample:  # 2x2 supersampling of the colour only
        dirs = camera_rays(R, width, height, K,
                            [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)])
    else:
        dirs = d_c[None]
    colour = mean_colour(scene, centre, dirs)
    image = np.round(np.clip(colour, 0.0, 1.0) * 255.0).astype(np.uint8).reshape(height, width, 3)
    return image, depth, obj.reshape(height, width), fc.reshape(height, width)


# ---------------------------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------------------------

def look_at(centre, target, roll):
    """World->camera rotation (OpenCV: x right, y down, z forward) looking from centre at target."""
    f = target - centre
    f /= np.linalg.norm(f)
    x = np.cross(f, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])  # rows: camera axes in world coordinates
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ R


def make_cameras(scene, num_views, seed):
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
        target = TABLE_CENTRE + rng.normal(0, [0.12, 0.12, 0.06])
        R = look_at(centre, target, rng.normal(0, np.deg2rad(2.0)))
        poses.append((R, -R @ centre))
    return poses
