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


def count_parameters(params: dict, alive: np.ndarray, banks: dict | None = None) -> dict:
    """Parameter counts by part.

    Returns:
      {"anchors", "mlps", "appearance", "query_heads", "memory_banks",
       "adapters", "total"} — anchors count alive anchors only (their centres
      included); memory banks count the PSC entries; adapters are the memory
      heads (key projection, temperature, adapter).
    """
    alive_count = int(np.sum(alive))
    anchors = sum(int(np.prod(x.shape[1:])) * alive_count
                  for x in jax.tree_util.tree_leaves(params["anchor"]))
    anchors += 3 * alive_count  # anchor centres are stored too, though not optimised

    def size(tree):
        return sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(tree))

    queries = params.get("queries", {})
    if "table" in queries:  # per-Gaussian queries: only alive anchors' rows
        query_heads = int(np.prod(queries["table"].shape[1:])) * alive_count
    else:
        query_heads = size(queries)
    parts = dict(anchors=anchors, mlps=size(params["decoder"]), appearance=size(params.get("appearance", {})),
                 query_heads=query_heads, memory_banks=size(banks or {}), adapters=size(params.get("memory", {})))
    parts["total"] = sum(parts.values())
    return parts


def evaluate_features(render, params, anchors, scene, views, banks: dict, feature_sets: dict, *,
                      out_dir: pathlib.Path | None = None, retrieval: bool = True) -> dict:
    """Table-2 style feature metrics on held-out views, with the mean-feature baseline and retrieval.

    Args:
      render: ``render(params, anchors, viewmat, K, appearance_index, banks) -> (rgb, {model: [H,W,D]})``.
      feature_sets: {model: FeatureSet} with maps [N, h, w, D] for every scene view.
      out_dir: if given, writes ``<model>_<view>.png`` (PCA of rendered | target).
      retrieval: also score open-vocabulary retrieval when the scene has object ids.
    Returns:
      {"models": {model: {"cosine", "l2", "baseline_cosine", "baseline_l2"}},
       "retrieval": {...} (demo scenes with object ids), "markdown": table}.
    """
    from cusgs_jax import feature_eval

    rendered = {name: [] for name in feature_sets}
    centers = scene.camera_centers
    for view in views:
        app = nearest_train_view(centers, scene.train_indices, view)
        _, feats = render(params, anchors, scene.viewmats[view], scene.Ks[view], app, banks)
        for name, fs in feature_sets.items():
            rendered[name].append(np.asarray(feats[name]))
    result = {"models": {}}
    lines = ["| model | cosine distance | L2 distance | mean-feature baseline cosine | baseline L2 |",
             "|---|---|---|---|---|"]
    for name, fs in feature_sets.items():
        h, w = fs.maps.shape[1:3]
        pred = feature_eval.resize_to(np.stack(rendered[name]), (h, w))
        target, valid = fs.maps[views], fs.valid[views]
        errors = feature_eval.feature_errors(pred, target, valid)
        mean_vec = feature_eval.mean_feature_baseline(fs.maps[scene.train_indices], fs.valid[scene.train_indices])
        base = feature_eval.baseline_errors(mean_vec, target, valid)
        result["models"][name] = dict(cosine=errors["cosine"], l2=errors["l2"],
                                      baseline_cosine=base["cosine"], baseline_l2=base["l2"])
        lines.append(f"| {name} | {errors['cosine']:.4f} | {errors['l2']:.4f} | {base['cosine']:.4f} | "
                     f"{base['l2']:.4f} |")
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            for k, view in enumerate(views):
                stem = pathlib.Path(scene.names[view]).stem
                feature_eval.save_feature_comparison(out_dir / f"{name}_{stem}.png", pred[k], target[k])
    ids_dir = pathlib.Path(scene.path) / "object_ids"
    if retrieval and ids_dir.is_dir():
        model = "semantic" if "semantic" in feature_sets else next(iter(feature_sets))
        fs = feature_sets[model]
        h, w = fs.maps.shape[1:3]
        ids = np.stack([np.load(ids_dir / (pathlib.Path(scene.names[v]).stem + ".npy")) for v in views])
        if ids.shape[1:] != (h, w):
            rows = (np.arange(h) + 0.5) * ids.shape[1] / h
            cols = (np.arange(w) + 0.5) * ids.shape[2] / w
            ids = ids[:, rows.astype(int)][:, :, cols.astype(int)]
        queries = feature_eval.object_queries(fs.maps[views], ids, fs.valid[views])
        pred = feature_eval.resize_to(np.stack(rendered[model]), (h, w))
        result["retrieval"] = dict(
            model=model,
            rendered=feature_eval.retrieval_scores(pred, ids, queries),
            ground_truth=feature_eval.retrieval_scores(fs.maps[views], ids, queries))
        lines += ["", f"Retrieval ({model} features, Otsu threshold):", "",
                  "| features | mIoU | cIoU | AP50 |", "|---|---|---|---|"]
        for row in ("rendered", "ground_truth"):
            r = result["retrieval"][row]
            lines.append(f"| {row} | {r['mIoU']:.3f} | {r['cIoU']:.3f} | {r['AP50']:.3f} |")
    result["markdown"] = "\n".join(lines) + "\n"
    return result
