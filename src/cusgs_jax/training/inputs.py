"""What a training run reads: the scene of its configuration (in the normalised frame), the feature maps and
their PSC banks, the training targets, the view order.

Naming (:mod:`cusgs_jax.types`): V views, h×w feature map, D feature dimension, M PSC entries.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging

import jax
import numpy as np

from cusgs_jax.config import Config, FeatureConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.features import FeatureSet, feature_dir, feature_file, load_features
from cusgs_jax.data.loader import load_scene, scene_folder
from cusgs_jax.data.normalize import WorldTransform, normalize_scene
from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.extract import BUILT_IN_EXTRACTORS, ensure_extracted
from cusgs_jax.memory import psc
from cusgs_jax.model.field import image_pixel_of
from cusgs_jax.splat.lens import Lens
from cusgs_jax.training.step import step_settings
from cusgs_jax.types import Camera

log = logging.getLogger("cusgs_jax")


def load_data(cfg: Config) -> tuple[SceneData, WorldTransform]:
    """The scene of ``data.path`` (or the built-in demo scene when it is None) in the normalised frame.

    ``data.path`` is read in its layout (``data.format``: COLMAP, Blender or nerfstudio, ``auto`` =
    detected; :func:`cusgs_jax.data.loader.load_scene`).

    Returns:
      (:class:`cusgs_jax.data.scene_data.SceneData` with extent 1, :class:`cusgs_jax.data.normalize.WorldTransform`
      from the scene's frame to it). Images with an alpha channel are composited on ``splat.background``, or
      when it is not set (None) on the layout's default (white for Blender, black otherwise), which
      ``scene.background`` records (:func:`resolve_background`).
    """
    data = cfg.data
    folder = scene_folder(data.path, data)  # the demo scene is generated here on first use
    if not data.path:
        log.info("using the built-in demo scene%s at %s", "" if data.demo.lens == "pinhole"
                 else f" through the {data.demo.lens} lens", folder)
    scene = load_scene(folder, data, background=cfg.splat.background, seed=cfg.train.seed)
    return normalize_scene(scene, align=data.align)


def resolve_background(cfg: Config, scene: SceneData) -> Config:
    """``cfg`` with ``splat.background`` = the colour ``scene``'s images were composited on when it was
    not set (None): the layout's default (white for Blender, black otherwise). A set colour is kept."""
    if cfg.splat.background is not None:
        return cfg
    color = tuple(float(c) for c in scene.background)
    if color != (0.0, 0.0, 0.0):
        log.info("splat.background not set: rendering on %s, the default of %s scenes", color,
                 scene.dataset_format)
    return cfg.replace(splat=dict(background=color))


def load_feature_targets(fcfg: FeatureConfig, scene: SceneData, seed: int, stage=None
                         ) -> tuple[dict[str, FeatureSet], dict[str, np.ndarray]]:
    """Feature maps of every configured model and their PSC banks.

    Missing built-in features are extracted first when ``fcfg.auto_extract``
    (the demo scene's default). The PSC scan sees a seeded random subset of the
    training pixels (``psc_rows``) in random order, so the ``max_bank_entries``
    cap samples the whole scene rather than its first views.

    A scene with distorted cameras needs features extracted from its images as this run loads them
    (their ``meta.json`` says ``"undistort": "mask"`` or ``"lens"``, nothing for crop:
    ``SceneData.camera_frame``; SceneError otherwise); with a valid-pixel mask
    (``data.undistort=mask``) the target vectors whose pixel lies outside it are zeroed — "no target"
    (:func:`mask_feature_maps`).

    ``stage``: ``stage("psc")`` is entered around each bank's construction (a run's time budget,
    :class:`cusgs_jax.app.budget.TimeBudget`), or None.

    Returns:
      (maps {model: FeatureSet}, banks {model: [M, D] float32 numpy}).
    """
    stage = stage or (lambda name: contextlib.nullcontext())
    maps, banks = {}, {}
    masked = scene.valid is not None
    frame = scene.camera_frame
    for index, model in enumerate(fcfg.model_list):
        # locked: the jobs of a parallel sweep share the demo scene's cache
        if fcfg.auto_extract and model.name in BUILT_IN_EXTRACTORS and ensure_extracted(
                scene, model.name, progress=False):
            log.info("extracted %s features for %s", model.name, scene.path)
        fs = load_features(scene.path, model.name, scene.names, image_size=(scene.width, scene.height))
        have = fs.meta.get("undistort", "crop")
        if have != frame:
            raise SceneError(
                f"the {model.name} features of {scene.path} were extracted from the images loaded with "
                f"data.undistort={have}, but this run uses data.undistort={frame}: re-extract them (cusgs-extract "
                f"{scene.path} --model {model.name} --undistort {frame} --overwrite) or set data.undistort={have}")
        if masked:
            fs = mask_feature_maps(fs, scene.valid)
        _warn_on_target_norms(scene.path, model.name, fs.maps, scene.names)  # every view: held-out ones are scored
        rows = fs.maps[scene.train_indices].reshape(-1, fs.dim)
        rows = rows[np.any(rows != 0, axis=-1)]
        rng = np.random.default_rng([seed, 7, index])
        rows = rows[rng.permutation(len(rows))[: fcfg.psc_rows]]
        with stage("psc"):
            bank = psc.build(rows, model.gamma, max_entries=fcfg.max_bank_entries)
        if bank.count == 0:
            raise ValueError(f"feature model {model.name!r}: no non-zero training targets to build a memory from")
        log.info("PSC %s: %d entries from %d pixels (gamma %.2f)", model.name, bank.count, len(rows), model.gamma)
        maps[model.name], banks[model.name] = fs, np.asarray(bank.entries, np.float32)
    return maps, banks


FLOAT16_MAX = float(np.finfo(np.float16).max)  # 65504
TARGET_NORM_MAX = 1e3
"""Largest feature target norm taken as plausible: the built-in extractors give norms ≤ 1 (descriptors,
semantic, vgg16); CLIP / DINOv2 tokens (LayerNorm outputs, √D ≈ 20 with unit gains) are expected at tens, an
estimate not measured on real weights; far larger targets make the feature loss dwarf the image
loss (and a single stray value makes some steps' loss explode)."""


def mask_feature_maps(fs: FeatureSet, valid: np.ndarray) -> FeatureSet:
    """``fs`` with the vectors of feature pixels outside the valid-pixel mask set to zero ("no target").

    Args:
      fs: feature maps [V, h, w, D] of the scene's views.
      valid: [V, H, W] bool valid-pixel masks of the images. A feature pixel (r, c) reads the image pixel
        whose centre is nearest to its own, as the loss samples it (:func:`cusgs_jax.model.field.image_pixel_of`).
    """
    fh, fw = fs.maps.shape[1:3]
    rows, cols = (np.asarray(i) for i in image_pixel_of(np.arange(fh), np.arange(fw), (fh, fw), valid.shape[1:]))
    keep = valid[:, rows][:, :, cols]  # [V, h, w]
    return dataclasses.replace(fs, maps=np.where(keep[..., None], fs.maps, 0).astype(fs.maps.dtype),
                               valid=fs.valid & keep)


def _warn_on_target_norms(scene_path, name: str, maps: np.ndarray, names) -> None:
    """Warn when the non-zero target vectors of ``maps`` [N, h, w, D] (feature model ``name``, views
    ``names``) have norms far above what the extractors produce (:data:`TARGET_NORM_MAX`): a scaled or
    corrupted feature folder. The message gives their range and the file holding the largest."""
    per_view = np.linalg.norm(maps.reshape(len(maps), -1, maps.shape[-1]).astype(np.float64), axis=-1)
    norms = per_view[per_view != 0]  # all-zero vectors: no target
    if not len(norms):
        return
    low, median, high = (float(v) for v in np.quantile(norms, [0.0, 0.5, 1.0]))
    if not np.isfinite(high) or high > TARGET_NORM_MAX:
        view = int(np.argmax(np.nan_to_num(per_view, nan=np.inf).max(axis=1)))
        worst = feature_file(scene_path, name, names[view])
        count = int(np.sum(~np.isfinite(norms) | (norms > TARGET_NORM_MAX)))
        log.warning("feature model %s: target vectors in %s have norms %.3g to %.3g (median %.3g); %d of %d are "
                    "above %g, far beyond what the extractors produce (at most a few tens; the largest is in %s): the "
                    "feature loss will dwarf the image loss or explode at the steps that sample them. Check the maps "
                    "(a stray value, a scale factor) or re-extract them with cusgs-extract", name,
                    feature_dir(scene_path, name), low, high, median, count, len(norms), TARGET_NORM_MAX, worst)


def feature_targets(feature_sets: dict[str, FeatureSet], views: np.ndarray) -> dict[str, jax.Array]:
    """{model: [V, h, w, D] device array} of the training views' feature maps.

    Stored as float16 (half the memory) unless a map holds values beyond
    float16's range (±65504), which would become inf: that model stays float32.
    """
    targets = {}
    for name, fs in feature_sets.items():
        maps = fs.maps[views]
        peak = float(np.max(np.abs(maps))) if maps.size else 0.0
        if peak > FLOAT16_MAX:
            log.info("feature model %s has values up to %.4g, beyond float16: its targets stay float32", name, peak)
            targets[name] = jax.device_put(maps.astype(np.float32))
        else:
            targets[name] = jax.device_put(maps.astype(np.float16))
    return targets


def view_order(seed: int, num_train: int, step: int) -> int:
    """Training view (position in the train list) used at ``step``.

    A fresh permutation per epoch, derived from (seed, epoch) alone, so a
    resumed run sees exactly the same sequence.
    """
    epoch, position = divmod(step, num_train)
    return int(np.random.default_rng([seed, epoch]).permutation(num_train)[position])


def make_batches(scene: SceneData, train_idx: np.ndarray, cfg: Config, targets: dict, banks: dict | None,
                 loss_terms=()):
    """``batch(step)``: the training views (``train_idx``, [V]) of ``step`` as the step's input
    (:func:`cusgs_jax.training.step.make_train_step`'s batch), with the feature ``targets`` ({model: [V, h, w, D]})
    and the memory ``banks`` when there are feature models (``banks`` not None). ``loss_terms``: research code's own
    terms (:class:`~cusgs_jax.training.loss_terms.LossTerm`), whose weights join ``"loss_weights"``.

    One view per step (:func:`view_order` at position ``step``) for ``train.batch_size = 1``; B > 1
    stacks the views at positions ``step·B … step·B + B − 1`` of the same epoch-wise permutation
    sequence (every view once per epoch of ⌈V/B⌉ steps, the same sequence on resume).
    """
    idx, size = train_idx, cfg.train.batch_size
    per_view = dict(image=scene.images[idx].astype(np.float32) / 255.0, K=np.asarray(scene.Ks[idx], np.float32),
                    viewmat=np.asarray(scene.viewmats[idx], np.float32))
    if scene.valid is not None:
        per_view["valid"] = scene.valid[idx]  # [V, H, W] bool
    if banks is not None:
        per_view["features"] = targets
    per_view = jax.device_put(per_view)  # transfers, not a program per array
    lens = None if scene.lens is None else Lens.of_views(scene.lens, idx)  # [V] lenses
    pick = jax.jit(lambda tree, view: jax.tree_util.tree_map(lambda a: a[view], tree))  # one program for every step
    # arguments of the step, not constants: a sweep over the loss weights, the learning rates or the seed shares
    # its program
    settings = step_settings(cfg, scene.extent, loss_terms)

    def batch(step: int) -> dict:
        if size == 1:
            view = np.int32(view_order(cfg.train.seed, len(idx), step))
        else:
            view = np.asarray([view_order(cfg.train.seed, len(idx), step * size + b) for b in range(size)],
                              np.int32)
        views = pick((per_view, lens), view)
        (picked, view_lens), view = views, jax.device_put(view)
        camera = Camera(picked["K"], picked["viewmat"], scene.width, scene.height, view_lens)
        out = dict(image=picked["image"], camera=camera, index=view, **settings)
        if "valid" in picked:
            out["valid"] = picked["valid"]
        if banks is not None:
            out["features"] = picked["features"]
            out["banks"] = banks
        return out

    return batch
