"""Held-out evaluation: PSNR/SSIM (and LPIPS when asked) per view, model size, render time, PNGs."""

from __future__ import annotations

import pathlib
import time

import imageio.v3 as iio
import jax
import numpy as np

from cusgs_jax.eval import metrics
from cusgs_jax.losses import zero_invalid
from cusgs_jax.model.anchors import AnchorState, parameter_counts
from cusgs_jax.types import Camera


def nearest_train_view(camera_centers: np.ndarray, train_indices: np.ndarray, view: int) -> int:
    """Position (in the training list) of the training camera closest to ``view``.

    Held-out views have no appearance embedding of their own; they borrow the
    nearest training camera's.
    """
    d = np.linalg.norm(camera_centers[train_indices] - camera_centers[view], axis=-1)
    return int(np.argmin(d))


def evaluate_views(render, anchors: AnchorState, nets: dict, scene, views, *, out_dir: pathlib.Path | None = None,
                   time_renders: bool = False, lpips: dict | None = None) -> dict:
    """PSNR and SSIM (and LPIPS) of ``views`` (indices into the scene).

    Args:
      render: ``render(anchors, nets, camera, appearance_index) -> (image [H,W,3],)``
        (:func:`cusgs_jax.training.render.make_render_fn`, which never drops work).
      scene: :class:`cusgs_jax.data.scene_data.SceneData`. With a valid-pixel mask (``scene.valid``),
        PSNR and SSIM run over the valid pixels (:func:`cusgs_jax.eval.metrics.psnr`, ``ssim``'s
        ``mask``) and LPIPS compares the two with the invalid pixels set to 0 in both.
      out_dir: if given, writes ``<name>.png`` with render | ground truth side by side.
      time_renders: also measure the median render time (after one warm-up).
      lpips: {key: fn} with ``fn(img0 [1,H,W,3], img1) -> [1]`` on images in [0, 1], e.g.
        :func:`cusgs_jax.eval.lpips.lpips_metrics` (built once per run; ``{}`` when the extra is
        missing); render and target are clipped to [0, 1] first. Not timed.
    Returns:
      {"per_view": [{name, psnr, ssim, <lpips keys>}], "psnr": mean, "ssim": mean,
       <lpips key>: mean for each lpips key, "render_ms_per_view": median or None}.
    """
    per_view, times = [], []
    centers = scene.camera_centers
    for view in views:
        app = nearest_train_view(centers, scene.train_indices, view)
        args = (anchors, nets, Camera.of_scene(scene, view), app)
        if time_renders and not times:
            jax.block_until_ready(render(*args))
        start = time.perf_counter()
        (image,) = jax.block_until_ready(render(*args))
        times.append(time.perf_counter() - start)
        image = np.asarray(image)
        target = scene.images[view].astype(np.float32) / 255.0
        valid = None if scene.valid is None else scene.valid[view]
        row = dict(name=scene.names[view], psnr=float(metrics.psnr(image, target, mask=valid)),
                   ssim=float(metrics.ssim(image, target, mask=valid)))
        # LPIPS has no mask: it compares the two images with their invalid pixels set to 0 in both
        scored, reference = np.clip(image, 0, 1), target
        if valid is not None:
            scored, reference = (np.asarray(x) for x in zero_invalid(scored, target, valid))
        for key, fn in (lpips or {}).items():
            row[key] = float(np.asarray(fn(scored[None], reference[None]))[0])
        per_view.append(row)
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            pair = np.concatenate([image, target], axis=1)
            iio.imwrite(out_dir / (pathlib.Path(scene.names[view]).stem + ".png"),
                        (np.clip(pair, 0, 1) * 255).round().astype(np.uint8))
    means = {key: float(np.mean([r[key] for r in per_view])) if per_view else float("nan")
             for key in ("psnr", "ssim", *(lpips or {}))}
    return dict(per_view=per_view, **means,
                render_ms_per_view=float(np.median(times) * 1e3) if time_renders and times else None)


def model_bytes(anchors: AnchorState, nets: dict, banks: dict | None = None) -> int:
    """Bytes of the model itself: what a viewer needs to render it, no optimiser state.

    The sum of ``nbytes`` over the alive anchors' rows of every per-anchor array (centres,
    offsets, scaling, latent, per-Gaussian query table), every network array in ``nets``
    (decoder MLPs, appearance embeddings, query heads, memory adapters) and the PSC
    ``banks`` ({model: [M, D]}). For float32 arrays it is 4 × :func:`count_parameters`'s
    ``total``. The checkpoint is larger: it also holds the Adam moments, dead anchor slots and
    the densification statistics.
    """
    alive = np.asarray(anchors.alive)
    per_anchor = [anchors.centers, anchors.params.offsets, anchors.params.log_scaling, anchors.params.latent]
    if anchors.params.query_table is not None:
        per_anchor.append(anchors.params.query_table)
    rows = sum(int(np.asarray(x)[alive].nbytes) for x in per_anchor)
    return rows + sum(int(np.asarray(x).nbytes) for x in jax.tree_util.tree_leaves((nets, banks or {})))


def count_parameters(anchors: AnchorState, nets: dict, banks: dict | None = None) -> dict:
    """Parameter counts by part.

    Returns:
      {"anchors", "mlps", "appearance", "query_heads", "memory_banks",
        "adapters", "total"} — anchors count alive anchors only (their centres
      included); query heads include a per-Gaussian query table's alive rows;
      memory banks count the PSC entries; adapters are the memory heads (key
      projection, temperature, adapter).
    """
    def size(tree):
        return sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(tree))

    per_anchor = parameter_counts(anchors)
    parts = dict(anchors=per_anchor["anchors"], mlps=size(nets["decoder"]), appearance=size(nets.get("appearance", {})),
                 query_heads=size(nets.get("queries", {})) + per_anchor["query_table"],
                 memory_banks=size(banks or {}), adapters=size(nets.get("memory", {})))
    parts["total"] = sum(parts.values())
    return parts
