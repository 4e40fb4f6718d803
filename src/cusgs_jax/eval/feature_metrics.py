"""Host-side evaluation of a trained feature field (NumPy only, no JAX).

What the paper's Table 2 and its retrieval protocol need, given features rendered by the field
and the target (teacher) features of the same views:

* :func:`feature_errors` — mean cosine distance and mean L2 distance over valid pixels;
* :func:`mean_feature_baseline`, :func:`baseline_errors` — the "predict the mean training
  feature everywhere" baseline a field has to beat;
* :func:`resize_to` — bring a render at image resolution to the targets' feature-map resolution;
* :func:`object_queries`, :func:`retrieval_scores` — text-free object retrieval (CUS-GS / M3
  protocol): cosine score maps against an object's mean target feature, Otsu threshold, IoU
  against the ground-truth object masks (mIoU, cIoU, AP50);
* :func:`similarity_mask` — the same score map and Otsu threshold for one query on one map (the
  viewer's click and text queries);
* :func:`pca_rgb`, :func:`save_feature_comparison` — false-colour pictures of feature maps.

Shapes: N views, h × w pixels (feature-map resolution), D feature dimension. As in
:mod:`cusgs_jax.data.features`, an all-zero target vector means "no target at this pixel".
Every function returns plain Python floats / NumPy arrays.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np

from cusgs_jax.data.features import resize_features

__all__ = [
    "COS_EPS",
    "baseline_errors",
    "feature_errors",
    "mean_feature_baseline",
    "object_queries",
    "pca_rgb",
    "resize_to",
    "retrieval_scores",
    "save_feature_comparison",
    "similarity_mask",
]

COS_EPS = 1e-8
"""Floor on ‖a‖·‖b‖ in cosine similarities: a zero vector has cosine 0 with everything
(cosine distance 1), never NaN."""


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _as_maps(x, name: str) -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 4:
        raise ValueError(f"{name} must be [N, h, w, D], got shape {arr.shape}")
    return arr


def _as_valid(valid, shape: tuple[int, ...], name: str = "valid") -> np.ndarray:
    """valid [N, h, w] bool, or all-True when None."""
    if valid is None:
        return np.ones(shape, bool)
    v = np.asarray(valid)
    if v.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {v.shape}")
    return v.astype(bool, copy=False)


def _cosine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine similarity along the last axis (float64), 0 where either vector is zero."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    dot = np.sum(a * b, axis=-1)
    norms = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    return dot / np.maximum(norms, COS_EPS)


# --------------------------------------------------------------------------------------------
# Feature errors and the mean-feature baseline
# --------------------------------------------------------------------------------------------


def feature_errors(pred, target, valid=None) -> dict:
    """Cosine and L2 distances between predicted and target features over valid pixels.

    Args:
      pred, target: [N, h, w, D] feature maps (same shape; resize a render first with
        :func:`resize_to`).
      valid: [N, h, w] bool, the pixels to score (typically ``FeatureSet.valid``: where the
        target is non-zero). None = every pixel.
    Returns:
      dict with
        "cosine": mean over all valid pixels of 1 − cos(pred, target), in [0, 2]. Computed with
          ‖p‖·‖t‖ floored at :data:`COS_EPS`, so a zero vector (either side) has cosine 0, i.e.
          distance 1, instead of NaN.
        "l2": mean over all valid pixels of ‖pred − target‖₂.
        "cosine_per_view", "l2_per_view": lists of N floats, the same means within each view
          (NaN for a view with no valid pixel).
        "num_valid": total number of valid pixels; "num_valid_per_view": list of N ints.
      The overall means pool the pixels of all views (a view with more valid pixels weighs
      more), so they equal the per-view means weighted by "num_valid_per_view", not their plain
      mean. They are NaN when no pixel is valid.
    """
    pred = _as_maps(pred, "pred")
    target = _as_maps(target, "target")
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {pred.shape} vs {target.shape} "
                         "(resize the render with resize_to first)")
    valid = _as_valid(valid, pred.shape[:3])
    cos_sum = l2_sum = 0.0
    count = 0
    cos_views: list[float] = []
    l2_views: list[float] = []
    n_views: list[int] = []
    for p, t, v in zip(pred, target, valid, strict=True):  # per view: bounded memory
        p = np.asarray(p[v], np.float64)
        t = np.asarray(t[v], np.float64)
        n = int(p.shape[0])
        cd = 1.0 - _cosine(p, t)
        l2 = np.linalg.norm(p - t, axis=-1)
        cos_views.append(float(cd.mean()) if n else float("nan"))
        l2_views.append(float(l2.mean()) if n else float("nan"))
        n_views.append(n)
        cos_sum += float(cd.sum())
        l2_sum += float(l2.sum())
        count += n
    return {
        "cosine": cos_sum / count if count else float("nan"),
        "l2": l2_sum / count if count else float("nan"),
        "cosine_per_view": cos_views,
        "l2_per_view": l2_views,
        "num_valid": count,
        "num_valid_per_view": n_views,
    }


def mean_feature_baseline(train_targets, train_valid=None) -> np.ndarray:
    """Mean of the valid training target vectors → [D] float64.

    Args:
      train_targets: [M, h, w, D] target features of the training views.
      train_valid: [M, h, w] bool (None = all pixels).
    Raises:
      ValueError: when no pixel is valid.
    """
    targets = _as_maps(train_targets, "train_targets")
    valid = _as_valid(train_valid, targets.shape[:3], "train_valid")
    count = int(valid.sum())
    if count == 0:
        raise ValueError("train_valid selects no pixel: there is no target to average")
    total = np.zeros(targets.shape[-1], np.float64)
    for t, v in zip(targets, valid, strict=True):
        total += np.asarray(t[v], np.float64).sum(axis=0)
    return total / count


def baseline_errors(mean_vec, target, valid=None) -> dict:
    """:func:`feature_errors` of predicting ``mean_vec`` [D] at every pixel of ``target``."""
    target = _as_maps(target, "target")
    mean_vec = np.asarray(mean_vec, np.float64)
    if mean_vec.shape != (target.shape[-1],):
        raise ValueError(f"mean_vec must be [D] = [{target.shape[-1]}], got {mean_vec.shape}")
    return feature_errors(np.broadcast_to(mean_vec, target.shape), target, valid)


# --------------------------------------------------------------------------------------------
# Resizing a render to the feature-map resolution
# --------------------------------------------------------------------------------------------


def resize_to(maps, size: tuple[int, int]) -> np.ndarray:
    """Area-average feature maps [N, H, W, D] (or [H, W, D]) to ``size = (h, w)``.

    Note the order: ``(h, w)`` — numpy-shape order, unlike
    :func:`cusgs_jax.data.features.resize_features`, which takes ``(w, h)`` and
    does the work (exact box filter). The same size returns the input itself.
    """
    arr = np.asarray(maps)
    h, w = (int(s) for s in size)
    if arr.ndim in (3, 4) and arr.shape[-3:-1] == (h, w):
        return arr
    return resize_features(arr, (w, h), method="area")


# --------------------------------------------------------------------------------------------
# Object retrieval
# --------------------------------------------------------------------------------------------


def object_queries(features, object_ids, valid=None) -> dict[int, np.ndarray]:
    """The retrieval query of every object: the mean feature of its valid pixels.

    Args:
      features: [N, h, w, D] (the *target* features, so the query is what the teacher model
        says about the object).
      object_ids: [N, h, w] int, 0 = no object.
      valid: [N, h, w] bool (None = all pixels).
    Returns:
      {object id (int, ≠ 0): [D] float64}, sorted by id; objects without a valid pixel are
      left out.
    """
    features = _as_maps(features, "features")
    ids = np.asarray(object_ids)
    if ids.shape != features.shape[:3]:
        raise ValueError(f"object_ids must have shape {features.shape[:3]}, got {ids.shape}")
    valid = _as_valid(valid, ids.shape)
    out: dict[int, np.ndarray] = {}
    for obj in np.unique(ids[valid]):
        if obj == 0:
            continue
        sel = valid & (ids == obj)
        out[int(obj)] = np.asarray(features[sel], np.float64).mean(axis=0)
    return out


def _unit_vectors(features: np.ndarray) -> np.ndarray:
    """[..., D] float32 unit feature vectors; zero vectors (norm below sqrt(COS_EPS)) stay zero."""
    feats = np.asarray(features, np.float32)
    norms = np.linalg.norm(feats, axis=-1, keepdims=True)
    tiny = np.float32(np.sqrt(COS_EPS))
    return np.where(norms >= tiny, feats / np.maximum(norms, tiny), np.float32(0.0))


def _retrieve(unit: np.ndarray, query, obj: int, ids: np.ndarray, valid: np.ndarray) -> tuple[float | None, int, int]:
    """One object of :func:`retrieval_scores`: (Otsu threshold or None, intersection, union).

    unit: [N, h, w, D] unit features; query: [D]; ids: [N, h, w] object ids; valid: [N, h, w] bool.
    """
    dim = unit.shape[-1]
    q = np.asarray(query, np.float64)
    if q.shape != (dim,):
        raise ValueError(f"query of object {obj} must be [D] = [{dim}], got {q.shape}")
    _, thr, pred = _scores_and_mask(unit, q, valid)
    gt = (ids == obj) & valid
    return thr, int(np.count_nonzero(pred & gt)), int(np.count_nonzero(pred | gt))


def _scores_and_mask(unit: np.ndarray, query: np.ndarray, valid: np.ndarray):
    """(cosine scores [...], Otsu threshold or None, mask [...] bool) of unit features [..., D] and a query [D].

    The threshold is Otsu's (``skimage.filters.threshold_otsu``) over the valid scores pooled;
    constant scores have nothing to separate: threshold None, empty mask.
    """
    from skimage.filters import threshold_otsu  # lazy

    qn = np.linalg.norm(query)
    q_unit = (query / qn if qn >= np.sqrt(COS_EPS) else np.zeros_like(query)).astype(np.float32)
    scores = unit @ q_unit  # cosine similarity
    pool = scores[valid]
    if pool.size == 0 or pool.min() == pool.max():
        return scores, None, np.zeros(scores.shape, bool)
    thr = float(threshold_otsu(pool))
    return scores, thr, (scores > thr) & valid


def similarity_mask(features, query, valid=None) -> tuple[np.ndarray, float | None, np.ndarray]:
    """One query against one feature map, as :func:`retrieval_scores` scores a view.

    Args:
      features: [h, w, D] feature map (e.g. rendered by the field at a viewer's camera).
      query: [D] query vector (a clicked pixel's feature, a text embedding).
      valid: optional [h, w] bool; pixels outside it take no part in the threshold and are never
        in the mask (None = all pixels).
    Returns:
      (scores [h, w] float32 cosine similarity (0 for a zero vector), Otsu threshold over the valid
      scores or None when they are constant, mask [h, w] bool = scores > threshold within valid).
    """
    features = np.asarray(features)
    if features.ndim != 3:
        raise ValueError(f"features must be [h, w, D], got shape {features.shape}")
    q = np.asarray(query, np.float64)
    if q.shape != (features.shape[-1],):
        raise ValueError(f"query must be [D] = [{features.shape[-1]}], got {q.shape}")
    return _scores_and_mask(_unit_vectors(features), q, _as_valid(valid, features.shape[:2]))


def retrieval_scores(features, object_ids, query_features: Mapping[int, np.ndarray], *,
                     valid=None) -> dict:
    """Retrieve each queried object by feature similarity and score the masks by IoU.

    For every object id in ``query_features``:

    1. score map = cosine similarity between each pixel's feature and the query (0 for a zero
       vector), in every view;
    2. threshold with Otsu's method (``skimage.filters.threshold_otsu``), computed **once per
       object on its score maps of all N views pooled together** — one threshold for the object
       across the scene, so a view where the object is absent (scores all low) predicts little
       instead of having its own background split in two; predicted mask = score > threshold.
       If all (valid) scores are equal there is nothing to separate: the prediction is empty;
    3. IoU of the predicted mask and the ground truth ``object_ids == id``, with the
       intersection and union pooled over all views. An object with union 0 (absent everywhere
       and not predicted) is skipped.

    Args:
      features: [N, h, w, D] features to search (e.g. rendered by the field, resized to the
        object-mask resolution).
      object_ids: [N, h, w] int ground-truth object ids, 0 = no object.
      query_features: {object id: [D] query vector}, e.g. from :func:`object_queries`.
      valid: optional [N, h, w] bool; pixels outside it take part in neither the threshold nor
        the IoU (None = all pixels).
    Returns:
      dict with
        "per_object": {id: IoU} for the objects not skipped;
        "mIoU": mean of those IoUs; "cIoU": Σ intersections / Σ unions over those objects;
        "AP50": fraction of those objects with IoU > 0.5 (all three NaN when every object was
          skipped);
        "thresholds": {id: Otsu threshold, or None where the scores were constant};
        "skipped": ids skipped because their union was 0.
    """
    features = _as_maps(features, "features")
    ids = np.asarray(object_ids)
    if ids.shape != features.shape[:3]:
        raise ValueError(f"object_ids must have shape {features.shape[:3]}, got {ids.shape}")
    valid = _as_valid(valid, ids.shape)
    unit = _unit_vectors(features)  # once for all queries

    per_object: dict[int, float] = {}
    thresholds: dict[int, float | None] = {}
    skipped: list[int] = []
    inter_sum = union_sum = 0
    for obj, query in query_features.items():
        obj = int(obj)
        thresholds[obj], inter, union = _retrieve(unit, query, obj, ids, valid)
        if union == 0:
            skipped.append(obj)
            continue
        per_object[obj] = inter / union
        inter_sum += inter
        union_sum += union
    ious = np.array(list(per_object.values()), np.float64)
    return {
        "per_object": per_object,
        "mIoU": float(ious.mean()) if ious.size else float("nan"),
        "cIoU": inter_sum / union_sum if union_sum else float("nan"),
        "AP50": float(np.mean(ious > 0.5)) if ious.size else float("nan"),
        "thresholds": thresholds,
        "skipped": skipped,
    }


# --------------------------------------------------------------------------------------------
# PCA pictures
# --------------------------------------------------------------------------------------------


def _pca_basis(vectors: np.ndarray, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Mean [D] and the first k principal directions [k, D] (rows; zero rows when D < k or the
    data has fewer directions). Signs fixed: each direction's largest-|·| loading is positive."""
    mean = vectors.mean(axis=0)
    centred = vectors - mean
    cov = centred.T @ centred / max(len(vectors), 1)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    order = np.argsort(evals)[::-1][:k]
    comps = evecs[:, order].T.copy()  # [min(k, D), D]
    for c in comps:
        if c[np.argmax(np.abs(c))] < 0:
            c *= -1
    if comps.shape[0] < k:
        comps = np.concatenate([comps, np.zeros((k - comps.shape[0], vectors.shape[1]))])
    return mean, comps


def pca_rgb(maps: Sequence[np.ndarray], fit_on: np.ndarray | None = None, *,
            percentiles: tuple[float, float] = (1.0, 99.0)) -> list[np.ndarray]:
    """False-colour images of feature maps through one 3-component PCA.

    The first three principal components are fitted on the valid (non-zero) vectors of
    ``fit_on`` (default ``maps[0]``); every map is projected on that same basis, so equal
    features get equal colours across images. Component c is mapped to [0, 255] with
    ``(x − lo_c) / (hi_c − lo_c)`` clipped, lo/hi = ``percentiles`` of the fit data's
    projections (a component with hi = lo, e.g. when D < 3, is mid-grey). Zero vectors are black.

    Args:
      maps: list of [h, w, D] arrays (sizes may differ, D may not).
      fit_on: [h, w, D] (or any [..., D]) array to fit the basis on.
    Returns:
      list of [h, w, 3] uint8 images.
    Raises:
      ValueError: when ``fit_on`` has no non-zero vector.
    """
    maps = [np.asarray(m) for m in maps]
    if not maps and fit_on is None:
        return []
    fit = np.asarray(maps[0] if fit_on is None else fit_on, np.float64)
    dim = fit.shape[-1]
    fit_vecs = fit.reshape(-1, dim)
    fit_vecs = fit_vecs[np.any(fit_vecs != 0, axis=-1)]
    if fit_vecs.shape[0] == 0:
        raise ValueError("fit_on has no non-zero feature vector to fit the PCA on")
    mean, comps = _pca_basis(fit_vecs)
    proj_fit = (fit_vecs - mean) @ comps.T
    lo = np.percentile(proj_fit, percentiles[0], axis=0)
    hi = np.percentile(proj_fit, percentiles[1], axis=0)
    span = hi - lo
    degenerate = span <= 1e-12 * max(1.0, float(np.abs(proj_fit).max()))
    out = []
    for m in maps:
        if m.ndim != 3 or m.shape[-1] != dim:
            raise ValueError(f"every map must be [h, w, {dim}], got shape {m.shape}")
        x = np.asarray(m, np.float64)
        proj = (x - mean) @ comps.T  # [h, w, 3]
        rgb = (proj - lo) / np.where(degenerate, 1.0, span)
        rgb = np.where(degenerate, 0.5, np.clip(rgb, 0.0, 1.0))
        rgb[~np.any(x != 0, axis=-1)] = 0.0
        out.append(np.round(rgb * 255.0).astype(np.uint8))
    return out


def save_feature_comparison(path: str | os.PathLike, predicted, target) -> pathlib.Path:
    """Write a PNG ``PCA(predicted) | PCA(target)`` side by side ([h, 2w, 3], no separator).

    The PCA basis and colour range are fitted on ``target``'s non-zero vectors, so a perfect
    prediction gives two identical halves. Both maps must be [h, w, D] of the same shape
    (resize a render with :func:`resize_to` first). Missing parent folders are created.
    Returns the path written.
    """
    import imageio.v3 as iio  # lazy

    predicted = np.asarray(predicted)
    target = np.asarray(target)
    if predicted.ndim != 3 or predicted.shape != target.shape:
        raise ValueError(f"predicted and target must both be [h, w, D] of one shape, got "
                         f"{predicted.shape} and {target.shape} (resize the render with resize_to)")
    left, right = pca_rgb([predicted, target], fit_on=target)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.concatenate([left, right], axis=1), extension=".png")
    return path
