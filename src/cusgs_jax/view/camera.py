"""A viser browser camera ↔ our :class:`cusgs_jax.types.Camera` (NumPy; both in OpenCV axes).

viser reports the browser's camera as ``wxyz`` (the rotation R of ``p_world = R p_camera + t``,
camera axes +z forward, +y down, +x right — OpenCV's, as ours), ``position`` (t) and ``fov``
(the vertical field of view in radians); the canvas has aspect W/H. The pinhole intrinsics of a
W×H render are then ``f = (H / 2) / tan(fov / 2)`` for both axes and the principal point at the
image centre, so the render fills the canvas exactly as three.js draws it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from cusgs_jax.types import Camera

__all__ = ["render_size", "intrinsics", "world_to_camera", "from_viser", "to_viser", "scene_up", "look_at_point"]


def render_size(aspect: float, height: int) -> tuple[int, int]:
    """(W, H) of a render ``height`` pixels high at the canvas aspect W/H (both ≥ 1)."""
    height = max(int(height), 1)
    return max(int(round(height * float(aspect))), 1), height


def intrinsics(fov_y: float, width: int, height: int) -> np.ndarray:
    """[3, 3] float32 K of a W×H image with vertical field of view ``fov_y`` (radians), centred."""
    f = 0.5 * height / np.tan(0.5 * float(fov_y))
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], np.float32)


def _quat_to_matrix(wxyz) -> np.ndarray:
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """[3, 3] rotation → wxyz (w ≥ 0), Shepperd's method."""
    r = np.asarray(r, np.float64)
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return q if q[0] >= 0 else -q


def world_to_camera(wxyz, position) -> np.ndarray:
    """[4, 4] float32 world→camera matrix of a camera at ``position`` with camera→world rotation ``wxyz``."""
    rot = _quat_to_matrix(wxyz)
    out = np.eye(4)
    out[:3, :3] = rot.T
    out[:3, 3] = -rot.T @ np.asarray(position, np.float64)
    return out.astype(np.float32)


def from_viser(wxyz, position, fov_y: float, width: int, height: int):
    """Our :class:`~cusgs_jax.types.Camera` of a viser camera rendered at W×H."""
    return Camera(jnp.asarray(intrinsics(fov_y, width, height)), jnp.asarray(world_to_camera(wxyz, position)),
                  int(width), int(height))


def to_viser(K, viewmat, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position, vertical fov) that put a viser camera where a training camera is.

    K [3, 3] and viewmat [4, 4] world→camera of an image ``height`` pixels high; an off-centre
    principal point is not representable in viser and is dropped.
    """
    viewmat = np.asarray(viewmat, np.float64)
    rot = viewmat[:3, :3].T
    position = -rot @ viewmat[:3, 3]
    fov = 2.0 * np.arctan(0.5 * height / float(np.asarray(K)[1, 1]))
    return _matrix_to_quat(rot), position, float(fov)


def scene_up(viewmats) -> np.ndarray:
    """[3] unit world "up" of a set of cameras: the mean of their −y axes (OpenCV's up) in world coordinates."""
    viewmats = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    up = -viewmats[:, 1, :3].mean(axis=0)  # row 1 of R_wc is the camera's +y axis in world coordinates
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, -1.0, 0.0])


def look_at_point(viewmat, target) -> np.ndarray:
    """[3] the point straight ahead of a camera at the depth of ``target`` [3] (an orbit centre).

    Never closer than a tenth of the distance to ``target``, so the orbit stays in front of the camera.
    """
    viewmat = np.asarray(viewmat, np.float64)
    rot = viewmat[:3, :3].T
    position = -rot @ viewmat[:3, 3]
    forward = rot[:, 2]
    offset = np.asarray(target, np.float64) - position
    depth = max(float(offset @ forward), 0.1 * float(np.linalg.norm(offset)), 1e-3)
    return position + depth * forward
