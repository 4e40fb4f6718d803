"""Training in a normalised world frame, so results do not depend on the scale of a COLMAP model.

**Why.** A COLMAP reconstruction has an arbitrary origin and scale: the same
capture can come out 1000× larger or smaller depending on the SfM run. The
method has quantities written in absolute world units — the voxel size ``l``,
the near plane, the volume regulariser ``mean(prod(scale))`` (cubic in the
unit), the grown cells ``l·16/4^i`` — so without care the same scene trains to
a different result at another scale (DESIGN.md §10: ×1000 trained to 9.8 dB).

**What we do** (gsplat's ``normalize_world_space``, translation and scale only):
every run works in the frame

    p' = s · (p − c),   c = mean camera centre,   s = 1 / extent,

where ``extent = 1.1 · max_i ‖C_i − c‖`` is the 3DGS/Scaffold-GS camera
extent. In this frame the cameras' extent is exactly 1, so every absolute
setting above is read in **units of the scene extent** (``model.voxel_size=0.01``
means 1 % of it). Camera poses keep their rotation; a world→camera matrix
``[R | t]`` becomes ``[R | s·(R c + t)]``, so camera-space depths scale by
``s`` and every projected pixel is unchanged. Rotations of the model are not
undone: the voxel grid stays aligned with the COLMAP axes (a rotated model
voxelises into a slightly different, equally fine scaffold).

When all cameras sit at one point (a single image, a tripod pan) the camera
extent is 0; the extent is then taken from the SfM points instead: 1.1 × the
90th percentile of their distance from the camera centre.

:class:`WorldTransform` records ``(s, c)``; an exporter applies
:meth:`WorldTransform.to_colmap` to put a model back into the COLMAP frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["WorldTransform", "normalize_scene", "camera_extent"]


@dataclasses.dataclass(frozen=True)
class WorldTransform:
    """``p_normalised = scale · (p_colmap − center)``.

    Attributes:
      scale: s > 0 (1 / the COLMAP-frame extent).
      center: [3] c, the mean camera centre in the COLMAP frame.
    """

    scale: float
    center: tuple[float, float, float]

    def to_normalized(self, points: np.ndarray) -> np.ndarray:
        """[..., 3] COLMAP-frame points → normalised frame (float64)."""
        return self.scale * (np.asarray(points, np.float64) - np.asarray(self.center))

    def to_colmap(self, points: np.ndarray) -> np.ndarray:
        """[..., 3] normalised-frame points → COLMAP frame (float64); lengths scale by ``1 / scale``."""
        return np.asarray(points, np.float64) / self.scale + np.asarray(self.center)

    def viewmats(self, viewmats: np.ndarray) -> np.ndarray:
        """[V, 4, 4] COLMAP world→camera → normalised world→camera: ``t' = s·(R c + t)``."""
        out = np.array(viewmats, np.float64)
        rot, trans = out[:, :3, :3], out[:, :3, 3]
        out[:, :3, 3] = self.scale * (rot @ np.asarray(self.center) + trans)
        return out

    def as_dict(self) -> dict:
        return {"scale": float(self.scale), "center": [float(x) for x in self.center]}


def camera_extent(camera_centers: np.ndarray, points: np.ndarray) -> tuple[float, np.ndarray]:
    """(extent, centre) of a scene: 1.1 × the largest camera distance from the mean camera centre.

    Falls back to the SfM points (1.1 × the 90th percentile of their distance from
    the centre) when the cameras do not span any distance.

    Args:
      camera_centers: [V, 3]; points: [P, 3].
    """
    centers = np.asarray(camera_centers, np.float64)
    center = centers.mean(axis=0)
    extent = 1.1 * float(np.max(np.linalg.norm(centers - center, axis=-1)))
    pts = np.asarray(points, np.float64)
    spread = float(np.percentile(np.linalg.norm(pts - center, axis=-1), 90)) if len(pts) else 0.0
    if not extent > 1e-6 * spread:
        extent = 1.1 * spread
    if not np.isfinite(extent) or extent <= 0:
        extent = 1.0  # one camera and every point at its centre: nothing to normalise by
    return extent, center


def normalize_scene(scene):
    """(scene in the normalised frame, :class:`WorldTransform`) of a :class:`~cusgs_jax.data.colmap.SceneData`.

    Images, intrinsics and the view split are untouched; ``points`` and
    ``viewmats`` move to the normalised frame and ``extent`` becomes 1.
    """
    extent, center = camera_extent(scene.camera_centers, scene.points)
    transform = WorldTransform(scale=1.0 / extent, center=tuple(float(x) for x in center))
    normalized = dataclasses.replace(
        scene,
        points=transform.to_normalized(scene.points).astype(np.float32),
        viewmats=transform.viewmats(scene.viewmats).astype(np.float32),
        extent=1.0,
    )
    return normalized, transform
