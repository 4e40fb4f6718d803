"""Feature-field evaluation on held-out views: Table-2 distances, the mean-feature baseline, retrieval.

Naming (:mod:`cusgs_jax.types`): V views, h×w feature-map size, D feature dimension.
"""

from __future__ import annotations

import pathlib

import numpy as np

from cusgs_jax.eval import feature_metrics
from cusgs_jax.eval.views import nearest_train_view
from cusgs_jax.model.anchors import AnchorState
from cusgs_jax.types import Camera


def evaluate_features(render, anchors: AnchorState, nets: dict, scene, views, banks: dict, feature_sets: dict, *,
                      out_dir: pathlib.Path | None = None, retrieval: bool = True) -> dict:
    """Table-2 style feature metrics on held-out views, with the mean-feature baseline and retrieval.

    Args:
      render: ``render(anchors, nets, camera, appearance_index, banks) -> (rgb, {model: [H,W,D]})``
        (:func:`cusgs_jax.training.render.make_feature_render_fn`).
      feature_sets: {model: FeatureSet} with maps [N, h, w, D] for every scene view.
      out_dir: if given, writes ``<model>_<view>.png`` (PCA of rendered | target).
      retrieval: also score open-vocabulary retrieval when the scene has object ids.
    Returns:
      {"models": {model: {"cosine", "l2", "baseline_cosine", "baseline_l2"}},
       "retrieval": {...} (demo scenes with object ids), "markdown": table}.
    """
    rendered = {name: [] for name in feature_sets}
    centers = scene.camera_centers
    for view in views:
        app = nearest_train_view(centers, scene.train_indices, view)
        _, feats = render(anchors, nets, Camera.of_scene(scene, view), app, banks)
        for name, fs in feature_sets.items():
            rendered[name].append(np.asarray(feats[name]))
    result = {"models": {}}
    lines = ["| model | cosine distance | L2 distance | mean-feature baseline cosine | baseline L2 |",
             "|---|---|---|---|---|"]
    for name, fs in feature_sets.items():
        h, w = fs.maps.shape[1:3]
        pred = feature_metrics.resize_to(np.stack(rendered[name]), (h, w))
        target, valid = fs.maps[views], fs.valid[views]
        errors = feature_metrics.feature_errors(pred, target, valid)
        mean_vec = feature_metrics.mean_feature_baseline(fs.maps[scene.train_indices], fs.valid[scene.train_indices])
        base = feature_metrics.baseline_errors(mean_vec, target, valid)
        result["models"][name] = dict(cosine=errors["cosine"], l2=errors["l2"],
                                      baseline_cosine=base["cosine"], baseline_l2=base["l2"])
        lines.append(f"| {name} | {errors['cosine']:.4f} | {errors['l2']:.4f} | {base['cosine']:.4f} | "
                     f"{base['l2']:.4f} |")
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            for k, view in enumerate(views):
                stem = pathlib.Path(scene.names[view]).stem
                feature_metrics.save_feature_comparison(out_dir / f"{name}_{stem}.png", pred[k], target[k])
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
        queries = feature_metrics.object_queries(fs.maps[views], ids, fs.valid[views])
        pred = feature_metrics.resize_to(np.stack(rendered[model]), (h, w))
        result["retrieval"] = dict(
            model=model,
            rendered=feature_metrics.retrieval_scores(pred, ids, queries),
            ground_truth=feature_metrics.retrieval_scores(fs.maps[views], ids, queries))
        lines += ["", f"Retrieval ({model} features, Otsu threshold):", "",
                  "| features | mIoU | cIoU | AP50 |", "|---|---|---|---|"]
        for row in ("rendered", "ground_truth"):
            r = result["retrieval"][row]
            lines.append(f"| {row} | {r['mIoU']:.3f} | {r['cIoU']:.3f} | {r['AP50']:.3f} |")
    result["markdown"] = "\n".join(lines) + "\n"
    return result
