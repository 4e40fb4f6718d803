"""Training in a normalised world frame, so results do not depend on the scale of a COLMAP model.

**Why.** A COLMAP reconstruction has an arbitrary origin and scale: the same
capture can come out 1000× larger or smaller depending on the SfM run. The
method has quantities written in absolute world units — the voxel size ``l``,
the near plane, the volume regulariser ``mean(prod(scale))`` (cubic in the
unit), the grown cells ``l·16/4^i`` — so without care the same scene trains to
a different result at another scale (docs/formats.md#scene-scale).

**What we do** (gsplat's ``normalize_world_space``, translation and scale only):
every run works in the frame

    p' = s · (p − c),   c = mean camera centre,   s = 1 / extent,

where ``extent = 1.1 · max_i ‖C_i − c‖`` is the 3DGS/Scaffold-GS camera
extent. In this frame the cameras' extent is exactly 1, so every absolute
setting above is read in **units of the scene extent** (``model.voxel_size=0.01``
means 1 % of it). A world→camera matrix ``[R | t]`` becomes ``[R | s·(R c + t)]``,
so camera-space depths scale by ``s`` and every projected pixel is unchanged.

**Rotation** (``data.align``). With ``none`` (the default) the frame keeps the
model's axes: the voxel grid is aligned with whatever axes the SfM run chose,
and a rotated model voxelises into a slightly different, equally fine scaffold.
With ``principal`` the frame is also rotated, ``p' = s · Q (p − c)``, onto the
principal axes of the SfM points about ``c`` (gsplat's ``align_principal_axes``;
the camera centres when there are fewer than 3 points): x along the largest
spread, z along the smallest — the vertical of a capture over a ground plane.
Each axis's sign makes the points' third moment along it non-negative and z is
flipped if needed to keep the frame right-handed, so the rule is equivariant: a
rotated copy of a model normalises to the same frame (tested). Poses become
``[R Qᵀ | s·(R c + t)]``. Exports undo ``Q`` with the rest (positions, Gaussian
rotations and SH colours: :func:`cusgs_jax.model.bake.to_colmap_frame`).

When all cameras sit at one point (a single image, a tripod pan) the camera
extent is 0; the extent is then taken from the SfM points instead: 1.1 × the
90th percentile of their distance from the camera centre.

:class:`WorldTransform` records ``(s, c)``; an exporter applies
:meth:`WorldTransform.to_colmap` to put a model back into the COLMAP frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cusgs_jax.config import DataConfig

__all__ = ["WorldTransform", "normalize_scene", "camera_centers", "camera_extent", "principal_axes", "ALIGNMENTS"]

ALIGNMENTS = ("none", "principal")
_IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclasses.dataclass(frozen=True)
class WorldTransform:
    """``p_normalised = scale · rotation · (p_colmap − center)``.

    Attributes:
      scale: s > 0 (1 / the COLMAP-frame extent).
      center: [3] c, the mean camera centre in the COLMAP frame.
      rotation: [3, 3] Q (rows: the normalised axes in COLMAP coordinates); the identity
        unless ``data.align=principal``.
    """

    scale: float
    center: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...] = _IDENTITY

    @property
    def matrix(self) -> np.ndarray:
        """[3, 3] float64 Q."""
        return np.asarray(self.rotation, np.float64)

    def to_normalized(self, points: np.ndarray) -> np.ndarray:
        """[..., 3] COLMAP-frame points → normalised frame (float64)."""
        return self.scale * (np.asarray(points, np.float64) - np.asarray(self.center)) @ self.matrix.T

    def to_colmap(self, points: np.ndarray) -> np.ndarray:
        """[..., 3] normalised-frame points → COLMAP frame (float64); lengths scale by ``1 / scale``."""
        return (np.asarray(points, np.float64) @ self.matrix) / self.scale + np.asarray(self.center)

    def viewmats(self, viewmats: np.ndarray) -> np.ndarray:
        """[V, 4, 4] COLMAP world→camera → normalised world→camera: ``[R Qᵀ | s·(R c + t)]``."""
        out = np.array(viewmats, np.float64)
        rot, trans = out[:, :3, :3], out[:, :3, 3]
        out[:, :3, 3] = self.scale * (rot @ np.asarray(self.center) + trans)
        out[:, :3, :3] = rot @ self.matrix.T
        return out

    def as_dict(self) -> dict:
        return {"scale": float(self.scale), "center": [float(x) for x in self.center],
                "rotation": [[float(x) for x in row] for row in self.rotation]}

    @staticmethod
    def from_dict(record: dict) -> WorldTransform:
        """The inverse of :meth:`as_dict` (records written before ``rotation`` existed: identity)."""
        rotation = record.get("rotation") or _IDENTITY
        return WorldTransform(float(record["scale"]), tuple(float(c) for c in record["center"]),
                              tuple(tuple(float(x) for x in row) for row in rotation))


def principal_axes(points: np.ndarray) -> np.ndarray:
    """[3, 3] float64 rotation Q whose rows are the principal axes of ``points`` [P, 3] about the origin.

    Rows by decreasing second moment; each row's sign makes ``Σ (p·q)³ ≥ 0``; the last row is
    flipped if needed so that ``det Q = +1``. Equivariant: ``principal_axes(p Mᵀ) = principal_axes(p) Mᵀ``
    for a rotation M (barring ties of moments, where the axes are not defined).
    """
    pts = np.asarray(points, np.float64)
    _, vectors = np.linalg.eigh(pts.T @ pts)
    axes = vectors[:, ::-1].T  # rows, largest second moment first
    skew = np.sum((pts @ axes.T) ** 3, axis=0)
    axes = axes * np.where(skew < 0, -1.0, 1.0)[:, None]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return axes


def camera_centers(viewmats: np.ndarray) -> np.ndarray:
    """[V, 3] float64 camera centres ``−Rᵀt`` of world→camera matrices ``viewmats`` [V, 4, 4]."""
    out = np.asarray(viewmats, np.float64)
    return -np.einsum("nji,nj->ni", out[:, :3, :3], out[:, :3, 3])


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


def normalize_scene(scene, align: str = DataConfig.align):
    """(scene in the normalised frame, :class:`WorldTransform`) of a :class:`~cusgs_jax.data.scene_data.SceneData`.

    Images, intrinsics and the view split are untouched; ``points`` and
    ``viewmats`` move to the normalised frame and ``extent`` becomes 1.

    Args:
      align: ``"none"`` keeps the model's axes; ``"principal"`` rotates onto the principal
        axes of the points (:func:`principal_axes`; of the camera centres with fewer than 3
        points) — ``data.align``.
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    extent, center = camera_extent(scene.camera_centers, scene.points)
    rotation = _IDENTITY
    if align == "principal":
        around = np.asarray(scene.points if len(scene.points) >= 3 else scene.camera_centers, np.float64) - center
        rotation = tuple(tuple(float(x) for x in row) for row in principal_axes(around))
    transform = WorldTransform(scale=1.0 / extent, center=tuple(float(x) for x in center), rotation=rotation)
    normalized = dataclasses.replace(
        scene,
        points=transform.to_normalized(scene.points).astype(np.float32),
        viewmats=transform.viewmats(scene.viewmats).astype(np.float32),
        extent=1.0,
    )
    return normalized, transform
