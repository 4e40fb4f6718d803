"""Cameras and camera paths for rendering a trained model (NumPy in, :class:`~cusgs_jax.types.Camera` out).

Conventions (docs/rasterizer.md#projection): OpenCV camera axes (+x right, +y down, +z forward), ``world_to_camera``
[4, 4], pinhole ``K`` [3, 3]. A trained model lives in the normalised training frame
(:class:`~cusgs_jax.data.normalize.WorldTransform`: camera extent 1); a pose from the scene's own frame comes over
with :func:`from_colmap` (a COLMAP world→camera pose) or :func:`from_blender` (a Blender/NeRF ``transform_matrix``,
camera→world in OpenGL axes). Paths: :func:`look_at`, :func:`orbit` (a circle around a point) and
:func:`interpolate_path` (key cameras joined: positions linearly, rotations by slerp), each a batched Camera
([B, 4, 4] / [B, 3, 3]) that :func:`cusgs_jax.render` renders in one call.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.types import Camera

__all__ = ["pinhole_K", "look_at", "orbit", "interpolate_path", "camera_path", "from_colmap", "from_blender",
           "stack_cameras"]


def pinhole_K(width: int, height: int, fov_y_degrees: float = 50.0) -> np.ndarray:
    """[3, 3] float32 intrinsics of a W×H image with vertical field of view ``fov_y_degrees``, centred."""
    if not 0.0 < float(fov_y_degrees) < 180.0:
        raise ValueError(f"fov_y_degrees={fov_y_degrees!r}: give an angle in (0, 180) degrees")
    f = 0.5 * int(height) / np.tan(0.5 * np.radians(float(fov_y_degrees)))
    return np.array([[f, 0.0, 0.5 * int(width)], [0.0, f, 0.5 * int(height)], [0.0, 0.0, 1.0]], np.float32)


def _look_at_matrix(eye, target, up) -> np.ndarray:
    """[4, 4] float64 world→camera of a camera at ``eye`` looking at ``target``, image up along ``up``."""
    eye, target, up = (np.asarray(v, np.float64).reshape(3) for v in (eye, target, up))
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError("look_at: eye and target are the same point; the camera has no direction")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)  # +x = forward × up for OpenCV's +y down (down = -up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: the view direction is parallel to up; give another up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot_wc = np.stack([right, down, forward])  # rows: the camera axes in world coordinates
    out = np.eye(4)
    out[:3, :3] = rot_wc
    out[:3, 3] = -rot_wc @ eye
    return out


def look_at(eye, target, up=(0.0, 0.0, 1.0), *, width: int = 640, height: int = 480,
            fov_y_degrees: float = 50.0, K=None) -> Camera:
    """A camera at ``eye`` [3] looking at ``target`` [3] with the image's up along ``up`` [3] (one camera)."""
    K = pinhole_K(width, height, fov_y_degrees) if K is None else np.asarray(K, np.float32)
    return Camera(jnp.asarray(K), jnp.asarray(_look_at_matrix(eye, target, up), jnp.float32), int(width),
                  int(height))


def stack_cameras(cameras) -> Camera:
    """One batched Camera (K [B, 3, 3], world_to_camera [B, 4, 4]) of single cameras of one image size."""
    cameras = list(cameras)
    if not cameras or len({(c.width, c.height) for c in cameras}) != 1:
        raise ValueError("stack_cameras: give one or more cameras of one image size")
    return Camera(jnp.stack([jnp.asarray(c.K) for c in cameras]),
                  jnp.stack([jnp.asarray(c.world_to_camera) for c in cameras]), cameras[0].width, cameras[0].height)


def orbit(center, radius: float, frames: int, *, up=(0.0, 0.0, 1.0), elevation_degrees: float = 20.0,
          width: int = 640, height: int = 480, fov_y_degrees: float = 50.0, K=None) -> Camera:
    """``frames`` cameras on a circle of ``radius`` around ``center`` [3], ``elevation_degrees`` above the plane
    normal to ``up``, each looking at ``center`` (a batch: B = frames)."""
    if int(frames) < 1 or not float(radius) > 0:
        raise ValueError(f"orbit: frames={frames!r} must be >= 1 and radius={radius!r} > 0")
    center, up = np.asarray(center, np.float64), np.asarray(up, np.float64) / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    elevation = np.radians(float(elevation_degrees))
    cams = []
    for t in np.arange(int(frames)) * 2.0 * np.pi / int(frames):
        direction = np.cos(elevation) * (np.cos(t) * a + np.sin(t) * b) + np.sin(elevation) * up
        cams.append(look_at(center + float(radius) * direction, center, up, width=width, height=height,
                            fov_y_degrees=fov_y_degrees, K=K))
    return stack_cameras(cams)


def _quaternion(rot: np.ndarray) -> np.ndarray:
    """[3, 3] rotation → unit quaternion wxyz (Shepperd's method)."""
    from cusgs_jax.view.camera import _matrix_to_quat  # one implementation of the conversion

    return _matrix_to_quat(rot)


def _rotation(q: np.ndarray) -> np.ndarray:
    from cusgs_jax.view.camera import _quat_to_matrix

    return _quat_to_matrix(q)


def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (the shorter arc)."""
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear, renormalised
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1.0 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta)


def interpolate_path(keys: Camera, frames: int) -> Camera:
    """``frames`` cameras along the key cameras ``keys`` (batched, B ≥ 2, in order): camera centres linearly,
    rotations by slerp, intrinsics linearly; the first and the last frame are the first and the last key."""
    viewmats, Ks = np.asarray(keys.world_to_camera, np.float64), np.asarray(keys.K, np.float64)
    if viewmats.ndim != 3 or len(viewmats) < 2 or int(frames) < 2:
        raise ValueError("interpolate_path: give two or more key cameras (batched) and frames >= 2")
    rots = viewmats[:, :3, :3]
    centers = -np.einsum("bji,bj->bi", rots, viewmats[:, :3, 3])  # c = -Rᵀ t
    quats = [_quaternion(r.T) for r in rots]  # camera→world rotations
    out_v, out_k = [], []
    for s in np.linspace(0.0, len(viewmats) - 1, int(frames)):
        i = min(int(np.floor(s)), len(viewmats) - 2)
        t = s - i
        rot_cw = _rotation(_slerp(quats[i], quats[i + 1], t))
        center = (1.0 - t) * centers[i] + t * centers[i + 1]
        m = np.eye(4)
        m[:3, :3] = rot_cw.T
        m[:3, 3] = -rot_cw.T @ center
        out_v.append(m)
        out_k.append((1.0 - t) * Ks[i] + t * Ks[i + 1])
    return Camera(jnp.asarray(np.stack(out_k), jnp.float32), jnp.asarray(np.stack(out_v), jnp.float32),
                  keys.width, keys.height)


def camera_path(cameras: Camera, kind: str = "orbit", frames: int = 60, *, width: int | None = None,
                height: int | None = None, elevation_degrees: float = 20.0) -> Camera:
    """A path around a set of cameras (a trained model's training cameras, batched): ``"orbit"`` circles the point
    they look at, at their mean distance from it, up along their mean up; ``"interpolate"`` passes through every
    one of them in order. ``width``/``height`` (default theirs) rescale the intrinsics."""
    from cusgs_jax.view.camera import look_at_point, scene_up

    viewmats = np.asarray(cameras.world_to_camera, np.float64)
    width, height = int(width or cameras.width), int(height or cameras.height)
    Ks = np.asarray(cameras.K, np.float64) * np.array([[width / cameras.width], [height / cameras.height], [1.0]])
    centers = -np.einsum("bji,bj->bi", viewmats[:, :3, :3], viewmats[:, :3, 3])
    if kind == "orbit":
        target = np.mean([look_at_point(v, centers.mean(axis=0)) for v in viewmats], axis=0)
        radius = float(np.mean(np.linalg.norm(centers - target, axis=-1)))
        fov = np.degrees(2.0 * np.arctan(0.5 * height / float(np.mean(Ks[:, 1, 1]))))
        return orbit(target, radius, frames, up=scene_up(viewmats), elevation_degrees=elevation_degrees,
                     width=width, height=height, fov_y_degrees=fov)
    if kind == "interpolate":
        return interpolate_path(Camera(jnp.asarray(Ks, jnp.float32), jnp.asarray(viewmats, jnp.float32), width,
                                       height), frames)
    raise ValueError(f"camera_path: kind={kind!r}; give 'orbit' or 'interpolate'")


def from_colmap(world: WorldTransform, world_to_camera, K, width: int, height: int) -> Camera:
    """A COLMAP pose (world→camera [4, 4] or [B, 4, 4] in the scene's frame, e.g. from ``images.txt``'s
    qvec/tvec) as a camera of the model's normalised training frame (``model.world``)."""
    viewmats = np.asarray(world_to_camera, np.float64)
    single = viewmats.ndim == 2
    moved = world.viewmats(viewmats.reshape(-1, 4, 4))
    K = np.broadcast_to(np.asarray(K, np.float32), (len(moved), 3, 3))
    moved, K = (moved[0], K[0]) if single else (moved, K)
    return Camera(jnp.asarray(K, jnp.float32), jnp.asarray(moved, jnp.float32), int(width), int(height))


def from_blender(world: WorldTransform, transform_matrix, K, width: int, height: int) -> Camera:
    """A Blender/NeRF ``transform_matrix`` (camera→world [4, 4], OpenGL camera axes) as a camera of the model's
    normalised training frame (``model.world``)."""
    c2w = np.array(transform_matrix, np.float64)
    c2w[:3, 1:3] *= -1.0  # OpenGL camera axes (y up, looking along -z) → OpenCV
    return from_colmap(world, np.linalg.inv(c2w), K, width, height)
