"""Carving random starting points: leave out the empty space the training views agree is empty.

A layout without points (Blender / NeRF-synthetic, nerfstudio without a PLY) starts from random points
(:mod:`cusgs_jax.data.random_points`), nearly all of them in empty space. Before any anchor is made,
:func:`carve` drops the points that the training views cannot hold:

* **outside every frustum**: behind every training camera or projecting outside every training image;
* **in front of transparent pixels, by a vote** (the visual hull; space carving, Kutulakos & Seitz, "A Theory
  of Shape by Space Carving"): where a view's image carries coverage in an alpha channel (NeRF-synthetic's
  RGBA), a point that projects onto a pixel whose alpha is 0 lies outside the object's silhouette there.
  Of the A views with alpha that see a point, let T show it transparent: the point is carved when
  ``T >= MIN_VOTES`` (2) **and** ``T >= VOTE_FRACTION · A`` (a twentieth) — or when A = T = 1, a point that
  only one view with alpha sees and that view shows transparent (no other witness; in an object-centric
  capture the object is seen by many views, so such a point lies off to the side of it).

Why a vote and not "any view": with "any", one wrong view — alpha 0 everywhere, a silhouette shifted by a
bad pose — carves away everything of the object inside its frustum (one blank view out of 100 left 5 of
100 000 points, none on the object, and a run 7 dB worse). A point of the object is covered in every
correct view, so T counts only the broken views there: it survives while they are fewer than 2 and fewer
than a twentieth of the views that see it — one bad view never carves a point that another view with alpha
sees, and with many views a few do not (4 of NeRF-synthetic's 100). The price is a looser hull, since a point
next to the object needs two transparent views (and a twentieth) to go: on the demo object capture
(:mod:`cusgs_jax.data.demo.objects` at 64 px: 60 views with alpha, 100 000 random points) "any view" keeps
2 708 points, two votes 3 067, two votes and a twentieth 3 309, a quarter 6 044, a half 12 374; 200-step runs
gave 24.31, 24.33, 24.25 and 24.06 dB held out for the first four (seed 0; 25.31, 25.33, 25.14 dB for the
2nd–4th with seed 1), so a twentieth costs nothing measurable where a quarter costs ~0.2 dB. On the analytic
sphere seen by 24 or 100 views (tests/data/test_carve.py) every point from 1.2 r out is carved, as by two
votes alone (a quarter: from 1.25 r, a half: from 1.4 r).

**Blank views**: a view with alpha whose coverage is empty or nearly so — under :data:`EMPTY_FRACTION`
(0.1 %) of its pixels, or under :data:`MEDIAN_FRACTION` (1/20) of the median coverage of the views with
alpha — is named in a warning and not used for carving by alpha (its frustum still counts, as a view
without alpha's does). An object-centric capture frames the object in every view, so such a view's alpha
is broken (an export without alpha, a wrong mask); even when it is right (a view that looks past the
object), leaving it out only keeps the empty space whose vote it would have decided. The
:class:`Carving` record lists them (``ignored_views``).

A point covered in every view that sees it survives — every point of the object, its surface included.
Coverage is dilated by :data:`COVERAGE_MARGIN` pixels (poses and the image's anti-aliasing are not exact to
a pixel), and a downscaled image's pixel counts as covered when any of the full-size pixels under it is.
Views without alpha carve by their frustum only. nerfstudio's ``mask_path`` is not coverage (it marks
pixels to leave out of the loss, behind which the scene goes on): it is never used here.

Projection is a ratio of lengths, so the result does not depend on the scene's scale, rotation or
origin (a similarity transform of points and cameras together carves the same points).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

log = logging.getLogger("cusgs_jax")

COVERAGE_MARGIN = 1  # pixels a view's coverage is grown by before carving
MIN_VOTES = 2  # a point is carved by at least this many views that show it transparent ...
VOTE_FRACTION = 0.05  # ... and by at least this fraction of the views with alpha that see it
EMPTY_FRACTION = 1e-3  # a view with alpha covering less of its pixels is blank: not used for carving
MEDIAN_FRACTION = 0.05  # ... as is one covering less than this fraction of the median view's coverage


@dataclasses.dataclass(frozen=True)
class Carving:
    """What :func:`carve` did (``eval.json``'s ``carving``).

    Attributes:
      points: random points before carving; kept: after it.
      outside_frusta: dropped because no training view sees them.
      transparent: dropped by the vote of the views with alpha that see them (transparent there).
      views_with_alpha: training views whose alpha carved (the ignored ones not counted).
      ignored_views: names of the training views whose alpha was blank or nearly so, not used for carving
        (absent from records written before it existed).
    """

    points: int
    kept: int
    outside_frusta: int
    transparent: int
    views_with_alpha: int
    ignored_views: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["ignored_views"] = list(self.ignored_views)
        return out


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


def blank_views(coverage: list[np.ndarray | None]) -> list[int]:
    """Indices of the views whose coverage is blank or nearly so (see the module docstring): covered
    fraction under :data:`EMPTY_FRACTION` or under :data:`MEDIAN_FRACTION` × the median over the views
    with alpha. Views without alpha (None) are never blank."""
    fractions = {i: float(np.mean(c)) for i, c in enumerate(coverage) if c is not None}
    if not fractions:
        return []
    median = float(np.median(list(fractions.values())))
    return [i for i, f in fractions.items() if f < EMPTY_FRACTION or f < MEDIAN_FRACTION * median]


def carve(points: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
          coverage: list[np.ndarray | None] | None = None, margin: int = COVERAGE_MARGIN,
          names: list[str] | None = None) -> tuple[np.ndarray, Carving]:
    """Which random points the training views can hold (see the module docstring).

    Args:
      points: [P, 3] points; viewmats: [V, 4, 4] world→camera (OpenCV axes) of the training views;
      Ks: [V, 3, 3] intrinsics at ``width`` × ``height``.
      coverage: per training view [H, W] bool (alpha > 0 at the loaded size) or None for a view without
        alpha; None: no view has alpha (frusta only).
      margin: pixels each view's coverage is dilated by.
      names: the V views' names (image files) for the warning and the record; None: "view <index>".
    Returns:
      (keep [P] bool, :class:`Carving`).
    """
    points = np.asarray(points, np.float64)
    coverage = list(coverage) if coverage is not None else [None] * len(viewmats)
    names = [str(n) for n in names] if names is not None else [f"view {i}" for i in range(len(viewmats))]
    ignored = blank_views(coverage)
    if ignored:
        with_alpha = [np.mean(c) for c in coverage if c is not None]
        log.warning("carving ignores %d of %d training views with alpha, whose alpha is blank or nearly so "
                    "(covered: %s; the median view %.3g%%): %s — their alpha is not used for carving, check those "
                    "images' alpha channel", len(ignored), len(with_alpha),
                    ", ".join(f"{100 * np.mean(coverage[i]):.3g}%" for i in ignored), 100 * np.median(with_alpha),
                    ", ".join(names[i] for i in ignored))
        coverage = [None if i in ignored else c for i, c in enumerate(coverage)]
    seen = np.zeros(len(points), bool)
    voters = np.zeros(len(points), np.int64)  # A: views with alpha that see the point
    votes = np.zeros(len(points), np.int64)  # T: those that show it transparent
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
            voters += inside
            votes += inside & ~grown[row, col]
    carved = (votes >= np.minimum(MIN_VOTES, voters)) & (votes >= VOTE_FRACTION * voters) & (votes > 0)
    keep = seen & ~carved
    return keep, Carving(points=len(points), kept=int(keep.sum()), outside_frusta=int((~seen).sum()),
                         transparent=int((seen & carved).sum()),
                         views_with_alpha=sum(c is not None for c in coverage),
                         ignored_views=tuple(names[i] for i in ignored))


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
