"""What a run starts from: ``setup(cfg, output_dir) -> Session``, an immutable value.

Setup checks the output folder and the checkpoints against ``train.resume``, reads the scene once
(:func:`cusgs_jax.training.inputs.load_data`), resolves every ``auto`` setting for it once
(:func:`cusgs_jax.app.resolve.resolve_for_scene`), loads the feature targets and PSC banks, and builds
the densification strategies and the batch schedule. It trains nothing and allocates no model: the
loop's state, which grows and is checkpointed, is made from the session by
:func:`cusgs_jax.app.loop.start`.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import pathlib
from collections.abc import Callable

import jax
import numpy as np

from cusgs_jax.app.ahead import Ahead
from cusgs_jax.app.budget import TimeBudget
from cusgs_jax.app.resolve import resolve_for_scene
from cusgs_jax.config import Config, require
from cusgs_jax.schedules import warn_schedules
from cusgs_jax.data.features import FeatureSet
from cusgs_jax.data.identity import scene_digest
from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.densify.base import Strategy
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.errors import UserError
from cusgs_jax.run_folder import CHECKPOINTS_DIR, CURVE_FILE, METRICS_FILE, read_eval, restore_hydra_record
from cusgs_jax.training.checkpoint import Checkpointer
from cusgs_jax.training.distributed import require_single_process
from cusgs_jax.training.inputs import feature_targets, load_data, load_feature_targets, make_batches
from cusgs_jax.training.loss_terms import LossTerm, check_loss_terms
from cusgs_jax.training.step import loss_weights
from cusgs_jax.training.parallel import resolve_devices

log = logging.getLogger("cusgs_jax")


@dataclasses.dataclass(frozen=True)
class Session:
    """What a run starts from, as setup leaves it; no field changes during the run.

    The budget, the checkpointer and the compile pool are objects with their own bookkeeping (the budget
    charges time, the checkpointer writes, the pool compiles); the loop's state is a
    :class:`cusgs_jax.app.loop.Loop`.
    """

    cfg: Config  # resolved for the scene (app/resolve.py)
    out: pathlib.Path
    scene: SceneData  # in the normalised training frame (extent 1)
    world: WorldTransform  # the scene's frame (COLMAP's) → the normalised training frame
    train_idx: np.ndarray  # [V] the training views (indices into the scene's views)
    test_idx: np.ndarray  # the evaluated views: held-out ones, or training views when there are none
    feature_sets: dict[str, FeatureSet]  # {feature model: its maps of every view}
    banks: dict[str, jax.Array] | None  # {feature model: [M, D] PSC entries}; None without feature models
    targets: dict[str, jax.Array]  # {feature model: [V, h, w, D] training targets (float16 unless too large)}
    strategies: tuple[Strategy, ...]  # the densification strategies, run in this order
    batches: Callable[[int], dict]  # batches(step): the training views of a step (make_batches)
    ckpt: Checkpointer
    budget: TimeBudget  # seconds per stage (eval.json's time) and the training clock
    ahead: Ahead | None = None  # the background compiles (app/ahead.py); None: every program compiles on its call
    loss_terms: tuple[LossTerm, ...] = ()  # research code's own loss terms (training/loss_terms.py)

    @property
    def evaluated_on(self) -> str:
        return "held_out" if len(self.scene.test_indices) else "train"

    @property
    def psnr_label(self) -> str:
        return "held-out PSNR" if self.evaluated_on == "held_out" else "training-view PSNR (no held-out views)"

    @functools.cached_property  # read after every step: computed once (the configuration and terms are fixed)
    def weights(self) -> dict:
        """The loss terms' weights ({term: float}, :func:`~cusgs_jax.training.step.loss_weights`): what
        :func:`~cusgs_jax.training.loss_terms.weighted_terms` weighs a step's terms by."""
        return {name: float(w) for name, w in loss_weights(self.cfg, self.loss_terms).items()}

    @property
    def devices(self) -> int:
        """Devices the step's views are sharded over (1 for a single-view step)."""
        return resolve_devices(self.cfg.train.batch_size, self.cfg.train.devices)

    def digest(self) -> str:
        """The training cameras' digest (:func:`cusgs_jax.data.identity.scene_digest`): checkpoints and eval.json."""
        scene, idx = self.scene, self.train_idx
        return scene_digest(scene.viewmats[idx], scene.Ks[idx], scene.width, scene.height)

    def cameras(self, idx) -> dict:
        """Views ``idx`` in the normalised frame: {"viewmats": [V, 4, 4], "Ks": [V, 3, 3], "width", "height"} as
        nested lists, and with ``data.undistort=lens`` of distorted cameras "lens": {"coeffs": [V, 6], "bounds": [V, 4],
        "fisheye"}."""
        scene = self.scene
        out = dict(viewmats=np.asarray(scene.viewmats, np.float64)[idx].tolist(),
                   Ks=np.asarray(scene.Ks, np.float64)[idx].tolist(), width=int(scene.width), height=int(scene.height))
        if scene.lens is not None:
            out["lens"] = scene.lens.as_dict(idx)
        return out


def setup(cfg: Config, output_dir, extra_strategies: tuple[Strategy, ...] = (),
          budget: TimeBudget | None = None, ahead: Ahead | None = None, *, loss_terms=()) -> Session:
    """The :class:`Session` a run of ``cfg`` in ``output_dir`` starts from.

    ``extra_strategies``: research code's own densification strategies
    (:class:`cusgs_jax.densify.base.Strategy`, unique names), run after the configured ones
    (:func:`~cusgs_jax.densify.factory.make_strategies`); a resume must pass the same ones.
    ``loss_terms``: research code's own loss terms (:class:`~cusgs_jax.training.loss_terms.LossTerm`); a
    resume passes the same ones. ``budget``: where the setup's stages are charged (:func:`cusgs_jax.app.run.run` passes the run's; default a
    new one). ``ahead``: the run's background compiles (:mod:`cusgs_jax.app.ahead`; default none).
    A refused setup puts the folder's accepted Hydra record back (:func:`~cusgs_jax.run_folder.restore_hydra_record`).
    """
    budget = budget or TimeBudget()
    warn_schedules(cfg)  # a schedule that never runs within train.iterations: one warning each
    loss_terms = check_loss_terms(loss_terms)
    require_single_process()
    devices = resolve_devices(cfg.train.batch_size, cfg.train.devices)  # train.devices=N with fewer: refused first
    if cfg.train.batch_size > 1:
        log.info("%d views per step, sharded over %d of %d device(s)", cfg.train.batch_size, devices,
                 jax.device_count())
    out = _output_folder(output_dir)
    try:
        return _setup(cfg, out, tuple(extra_strategies), budget, ahead, loss_terms)
    except UserError:  # refused: the folder's Hydra record goes back to the run it holds
        restore_hydra_record(out)
        raise


def _setup(cfg: Config, out: pathlib.Path, extra_strategies: tuple[Strategy, ...], budget: TimeBudget,
           ahead: Ahead | None, loss_terms: tuple[LossTerm, ...] = ()) -> Session:
    ckpt = Checkpointer(cfg.train.checkpoint_dir or out / CHECKPOINTS_DIR)
    cfg = _require_resumable(cfg, ckpt, out)
    with budget.stage("load"):
        scene, world = load_data(cfg)
        cfg = resolve_for_scene(cfg, scene).cfg  # every auto setting, once (app/resolve.py)
    train_idx = scene.train_indices
    test_idx = scene.test_indices if len(scene.test_indices) else spread(train_idx, 8)
    log.info("scene %s (%s): %d train / %d held-out views at %dx%d, %d points; extent %.4g in the scene's frame "
             "(trained in units of it), voxel size %.4g", scene.path, scene.dataset_format, len(train_idx),
             len(scene.test_indices), scene.width, scene.height, len(scene.points), 1.0 / world.scale,
             cfg.model.voxel_size)
    if not len(scene.test_indices):
        log.warning("no held-out views (data.holdout_every=%d): the reported PSNR/SSIM are measured on "
                    "training views and say nothing about novel views", cfg.data.holdout_every)
    feature_sets, banks, targets = {}, None, {}
    if cfg.features.enabled:
        with budget.stage("features"):
            feature_sets, banks = load_feature_targets(cfg.features, scene, cfg.train.seed, stage=budget.stage)
            targets = feature_targets(feature_sets, train_idx)
            banks = {name: jax.device_put(np.asarray(b, np.float32)) for name, b in banks.items()}
    strategies = make_strategies(cfg) + extra_strategies
    names = [s.name for s in strategies]
    if len(set(names)) != len(names):
        raise ValueError(f"densification strategies need unique names (TrainState.densify is keyed by them): {names}")
    return Session(cfg=cfg, out=out, scene=scene, world=world, train_idx=train_idx, test_idx=test_idx,
                   feature_sets=feature_sets, banks=banks, targets=targets, strategies=strategies,
                   batches=make_batches(scene, train_idx, cfg, targets, banks, loss_terms), ckpt=ckpt, budget=budget,
                   ahead=ahead, loss_terms=loss_terms)


def _require_resumable(cfg: Config, ckpt: Checkpointer, out: pathlib.Path) -> Config:
    """``train.resume`` agrees with the checkpoints there are, and a resumed folder's record is one this version
    reads (a newer or damaged one is refused here, not overwritten). Returns the config the run goes on with: a
    resume before the first checkpoint (a job killed early) starts afresh, with a warning, its killed run's log
    rows removed (the fresh run logs those steps again)."""
    latest = ckpt.latest_step()
    if cfg.train.resume and latest is None:
        log.warning("train.resume=true: no checkpoint yet in %s: starting afresh", ckpt.directory)
        cfg = cfg.replace(train=dict(resume=False))
        for name in (METRICS_FILE, CURVE_FILE):
            (out / name).unlink(missing_ok=True)
    require(cfg.train.resume or latest is None, "train.resume", False,
            f"{ckpt.directory} already holds checkpoints of an earlier run (newest: step {latest})",
            "continue it with train.resume=true, or start afresh in a new folder (hydra.run.dir=...)")
    require_not_past(cfg, latest, ckpt.directory)
    if cfg.train.resume:
        read_eval(out)
    return cfg


def require_not_past(cfg: Config, step: int | None, directory) -> None:
    """A resumed run cannot train backwards: refuse a checkpoint already past ``train.iterations``."""
    require(not cfg.train.resume or step is None or step <= cfg.train.iterations, "train.iterations",
            cfg.train.iterations, f"the run to resume in {directory} is already at step {step}, past the asked "
            "iterations (resuming cannot undo steps, and its eval.json would report a model of more steps)",
            f"set train.iterations={step} or more to continue it, or train {cfg.train.iterations} steps in a new "
            "output folder (hydra.run.dir=...)")


def _output_folder(output_dir) -> pathlib.Path:
    out = pathlib.Path(output_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / ".write_test").touch()
        (out / ".write_test").unlink()
    except OSError as error:
        require(False, "hydra.run.dir", str(out), f"the output folder cannot be written ({error.strerror})",
                "run from a writable folder or set hydra.run.dir=<a writable folder>")
    return out


def spread(indices: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` entries of ``indices`` spread evenly over it."""
    return indices[np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))]
