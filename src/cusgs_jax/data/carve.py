"""Carving random starting points: leave out the empty space no training view can hold.

A layout without points (Blender / NeRF-synthetic, nerfstudio without a PLY) starts from random points
(:mod:`cusgs_jax.data.random_points`), nearly all of them in empty space. Before any anchor is made,
:func:`carve` drops the points that no training view can explain:

* **outside every frustum**: behind every training camera or projecting outside every training image;
* **in front of a transparent pixel** (the visual hull; space carving, Kutulakos & Seitz, "A Theory of
  Shape by Space Carving"): where a view's image carries coverage in an alpha channel (NeRF-synthetic's
  RGBA), a point that projects onto a pixel whose alpha is 0 in *any* training view that sees it lies
  outside the object's silhouette there, so in empty space.

A point that lands on a covered pixel of every view that sees it survives — every point of the object,
its surface included. Coverage is dilated by :data:`COVERAGE_MARGIN` pixels (poses and the image's
anti-aliasing are not exact to a pixel), and a downscaled image's pixel counts as covered when any of
the full-size pixels under it is. Views without alpha carve by their frustum only. nerfstudio's
``mask_path`` is not coverage (it marks pixels to leave out of the loss, behind which the scene goes
on): it is never used here.

Projection is a ratio of lengths, so the result does not depend on the scene's scale, rotation or
origin (a similarity transform of points and cameras together carves the same points).
"""

from __future__ import annotations

import dataclasses

import numpy as np

COVERAGE_MARGIN = 1  # pixels a view's coverage is grown by before carving


@dataclasses.dataclass(frozen=True)
class Carving:
    """What :func:`carve` did (``eval.json``'s ``carving``).

    Attributes:
      points: random points before carving; kept: after it.
      outside_frusta: dropped because no training view sees them.
      transparent: dropped because a view that sees them shows a transparent pixel there.
      views_with_alpha: training views whose images carry coverage.
    """

    points: int
    kept: int
    outside_frusta: int
    transparent: int
    views_with_alpha: int

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """[H, W] bool ``mask`` grown by ``pixels`` in each direction (a square neighbourhood)."""
    out = mask.copy()
    for _ in range(pixels):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= grown[:, :-1].copy()
        grown[:, :-1] |= grown[:, 1:].copy()
        out = grown
    return out


def carve(points: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
          coverage: list[np.ndarray | None] | None = None, margin: int = COVERAGE_MARGIN
          ) -> tuple[np.ndarray, Carving]:
    """Which random points a training view can hold (see the module docstring).

    Args:
      points: [P, 3] points; viewmats: [V, 4, 4] world→camera (OpenCV axes) of the training views;
      Ks: [V, 3, 3] intrinsics at ``width`` × ``height``.
      coverage: per training view [H, W] bool (alpha > 0 at the loaded size) or None for a view without
        alpha; None: no view has alpha (frusta only).
      margin: pixels each view's coverage is dilated by.
    Returns:
      (keep [P] bool, :class:`Carving`).
    """
    points = np.asarray(points, np.float64)
    coverage = list(coverage) if coverage is not None else [None] * len(viewmats)
    seen = np.zeros(len(points), bool)
    carved = np.zeros(len(points), bool)
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    for viewmat, K, covered in zip(np.asarray(viewmats, np.float64), np.asarray(Ks, np.float64), coverage):
        cam = homogeneous @ viewmat[:3].T  # [P, 3] camera coordinates
        z = cam[:, 2]
        front = z > 0
        safe = np.where(front, z, 1.0)
        u = K[0, 0] * cam[:, 0] / safe + K[0, 2]
        v = K[1, 1] * cam[:, 1] / safe + K[1, 2]
        inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        seen |= inside
        if covered is not None:
            grown = dilate(np.asarray(covered, bool), margin)
            col = np.clip(np.floor(u), 0, width - 1).astype(np.int64)
            row = np.clip(np.floor(v), 0, height - 1).astype(np.int64)
            carved |= inside & ~grown[row, col]
    keep = seen & ~carved
    return keep, Carving(points=len(points), kept=int(keep.sum()), outside_frusta=int((~seen).sum()),
                         transparent=int((seen & carved).sum()),
                         views_with_alpha=sum(c is not None for c in coverage))


def coverage_at(alpha: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """[h, w] bool coverage of an [H, W] alpha (in [0, 1]) at the loaded size ``out_hw``: a loaded pixel is
    covered when any full-size pixel under it has alpha > 0 (nearest blocks; exact for integer factors)."""
    covered = np.asarray(alpha) > 0
    H, W = covered.shape
    h, w = out_hw
    if (h, w) == (H, W):
        return covered
    rows = np.minimum((np.arange(H) * h) // H, h - 1)
    cols = np.minimum((np.arange(W) * w) // W, w - 1)
    out = np.zeros((h, w), bool)
    np.logical_or.at(out, (rows[:, None], cols[None, :]), covered)
    return out
