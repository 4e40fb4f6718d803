"""Held-out evaluation: PSNR/SSIM per view, model size, render time, PNGs."""

from __future__ import annotations

import pathlib
import time

import imageio.v3 as iio
import jax
import numpy as np

from cusgs_jax import metrics


def nearest_train_view(camera_centers: np.ndarray, train_indices: np.ndarray, view: int) -> int:
    """Position (in the training list) of the training camera closest to ``view``.

    Held-out views have no appearance embedding of their own; they borrow the
    nearest training camera's.
    """
    d = np.linalg.norm(camera_centers[train_indices] - camera_centers[view], axis=-1)
    return int(np.argmin(d))


def evaluate_views(render, params, anchors, scene, views, *, out_dir: pathlib.Path | None = None,
                   time_renders: bool = False) -> dict:
    """PSNR and SSIM of ``views`` (indices into the scene).

    Args:
      render: ``render(params, anchors, viewmat, K, appearance_index) -> (image [H,W,3], overflow)``.
      scene: :class:`cusgs_jax.data.colmap.SceneData`.
      out_dir: if given, writes ``<name>.png`` with render | ground truth side by side.
      time_renders: also measure the median render time (after one warm-up).
    Returns:
      {"per_view": [{name, psnr, ssim}], "psnr": mean, "ssim": mean,
       "render_ms_per_view": median or None, "overflow": total}.
    """
    per_view, times, overflow = [], [], 0
    centers = scene.camera_centers
    for view in views:
        app = nearest_train_view(centers, scene.train_indices, view)
        args = (params, anchors, scene.viewmats[view], scene.Ks[view], app)
        if time_renders and not times:
            jax.block_until_ready(render(*args))
        start = time.perf_counter()
        image, ovf = jax.block_until_ready(render(*args))
        times.append(time.perf_counter() - start)
        image = np.asarray(image)
        target = scene.images[view].astype(np.float32) / 255.0
        overflow += int(ovf)
        row = dict(name=scene.names[view], psnr=float(metrics.psnr(image, target)),
                   ssim=float(metrics.ssim(image, target)))
        per_view.append(row)
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            pair = np.concatenate([image, target], axis=1)
            iio.imwrite(out_dir / (pathlib.Path(scene.names[view]).stem + ".png"),
                        (np.clip(pair, 0, 1) * 255).round().astype(np.uint8))
    return dict(
        per_view=per_view,
        psnr=float(np.mean([r["psnr"] for r in per_view])) if per_view else float("nan"),
        ssim=float(np.mean([r["ssim"] for r in per_view])) if per_view else float("nan"),
        render_ms_per_view=float(np.median(times) * 1e3) if time_renders and times else None,
        overflow=overflow,
    )


def count_parameters(params: dict, alive: np.ndarray) -> dict:
    """Parameter counts: alive anchors' arrays, decoder MLPs, appearance embeddings.

    Returns:
      {"anchors": int, "mlps": int, "appearance": int, "total": int}.
    """
    alive_count = int(np.sum(alive))
    anchors = sum(int(np.prod(x.shape[1:])) * alive_count
                  for x in jax.tree_util.tree_leaves(params["anchor"]))
    mlps = sum(int(x.size) for x in jax.tree_util.tree_leaves(params["decoder"]))
    appearance = int(params["appearance"].size) if "appearance" in params else 0
    # anchor centres are stored too (3 floats each), though not optimised
    anchors += 3 * alive_count
    return dict(anchors=anchors, mlps=mlps, appearance=appearance, total=anchors + mlps + appearance)
