"""A trained model back from its run folder, without the scene (for exporters and viewers).

A run folder (``cusgs-train`` or :func:`cusgs_jax.app.run.run`) holds:

* ``checkpoints/<step>/`` — orbax checkpoints of the whole training state; only
  the anchors and the networks are read (not the optimiser moments), read-only
  (:func:`cusgs_jax.training.checkpoint.read_arrays`);
* ``.hydra/config.yaml`` — the composed configuration (runs started by
  ``cusgs-train``); runs started from Python have it in the checkpoint metadata
  (``config``) instead; without either the defaults are used. Either way the
  decoder's shape (N offsets, latent size, hidden width, appearance size) is
  read off the stored arrays, so it always matches the weights;
* ``eval.json`` — ``world_transform`` ({scale, center, rotation}: ``p_normalised =
  scale·(p_colmap − center)``) and the resolved ``voxel_size``; checkpoints
  written since the exporter exists record both in their metadata as well, so an
  unfinished run loads too.

The training cameras (:attr:`TrainedModel.cameras`; the exporter bakes
opacities and shapes over them) come from the checkpoint metadata
(``train_cameras``, written since the exporter exists); for an older run they are
read from the scene's COLMAP model at ``data.path`` (the demo scene's cache
folder when it is unset) if it is still there — poses and intrinsics only, no
image is read and nothing is generated. Otherwise they are None.

Nothing reads the images or the feature targets.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets per anchor, F
latent size, V training views, E appearance size.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pathlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from omegaconf import DictConfig, OmegaConf

from cusgs_jax.config import Config
from cusgs_jax.compose import from_dict, from_omegaconf
from cusgs_jax.data.loader import load_cameras, scene_folder
from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.errors import CheckpointError, UserError
from cusgs_jax.run_folder import BANKS_FILE, CHECKPOINTS_DIR, HYDRA_DIR, CheckpointMeta, EvalRecord, read_eval
from cusgs_jax.model.anchors import AnchorParams, AnchorState, compact
from cusgs_jax.splat.lens import Lens
from cusgs_jax.training.checkpoint import read_arrays
from cusgs_jax.types import Camera

__all__ = ["TrainedModel", "load_trained", "BANKS_FILE"]


log = logging.getLogger("cusgs_jax")


@dataclasses.dataclass(frozen=True)
class TrainedModel:
    """A trained model as the run left it, in the normalised training frame.

    Attributes:
      cfg: the run's :class:`~cusgs_jax.config.Config` (``model.voxel_size`` resolved
        when the run recorded it; decoder shape as stored).
      anchors: :class:`~cusgs_jax.model.anchors.AnchorState`, compacted to the alive
        anchors (:func:`~cusgs_jax.model.anchors.compact`: capacity A a multiple of 64,
        the padding slots dead): centers [A, 3], alive [A], params.offsets [A, N, 3],
        params.log_scaling [A, 6], params.latent [A, F], params.query_table [A, N, Q] or None.
      nets: {"decoder": {"opacity", "cov", "color"} MLP params, "appearance"?: [V, E]
        per training view, "queries"?, "memory"?} as jax arrays.
      world: :class:`~cusgs_jax.data.normalize.WorldTransform` back to the COLMAP
        frame, or None when the run recorded none.
      step: the checkpoint's step.
      run_dir: the run folder; checkpoint_dir: the folder of the checkpoints.
      checkpoint_bytes: size on disk of the checkpoint read (optimiser state included).
      evaluation: the run's record (``eval.json``: :class:`~cusgs_jax.run_folder.EvalRecord`), or None (unfinished run).
      cameras: the V training cameras in the normalised frame as one batched
        :class:`~cusgs_jax.types.Camera` (K [V, 3, 3], world_to_camera [V, 4, 4], static
        width/height, and for a ``data.undistort=lens`` run of distorted cameras their ``lens``), or None when
        neither the checkpoint nor the scene gives them.
      cameras_from: "checkpoint", the scene folder they were read from, or None.
      held_out_cameras: the held-out cameras (batched Camera) as the checkpoint records them
        (``held_out_cameras``, written since the viewer exists), or None (none held out, or an older run).
      banks: {feature model: [M, D] PSC entries} from ``feature_banks.npz``, or None (no feature
        model, or a run older than the file).
    """

    cfg: Config
    anchors: AnchorState
    nets: dict[str, Any]
    world: WorldTransform | None
    step: int
    run_dir: pathlib.Path
    checkpoint_dir: pathlib.Path
    checkpoint_bytes: int
    evaluation: EvalRecord | None
    cameras: Camera | None = None
    cameras_from: str | None = None
    held_out_cameras: Camera | None = None
    banks: dict[str, np.ndarray] | None = None

    @property
    def num_anchors(self) -> int:
        """Alive anchors."""
        return int(np.sum(np.asarray(self.anchors.alive)))

    def mean_appearance(self) -> jax.Array | None:
        """[E] mean of the training views' appearance embeddings, or None without the embedding.

        The decoder's colour head takes a per-training-camera embedding; a view
        that is none of them (an exporter's, a viewer's) has no embedding of its
        own, and the mean is the one that belongs to no view in particular.
        """
        if "appearance" not in self.nets:
            return None
        return jnp.mean(self.nets["appearance"], axis=0)


def load_trained(run_dir: str | os.PathLike, *, step: int | None = None) -> TrainedModel:
    """Load the newest checkpoint (or ``step``) of a run folder as a :class:`TrainedModel`.

    Args:
      run_dir: a run folder written by ``cusgs-train`` (or :func:`cusgs_jax.app.run.run`).
      step: a given checkpoint step; None: the newest one that reads cleanly.
    Raises:
      UserError (:class:`~cusgs_jax.errors.CheckpointError` for checkpoint problems):
        not a folder, no checkpoint, damaged checkpoints, a config or eval.json that
        cannot be read, or stored arrays that are not a cusgs-jax model — the folder named.
    """
    if step is not None and (isinstance(step, bool) or not isinstance(step, (int, np.integer))):
        raise TypeError(f"load_trained: step must be an int (a checkpoint's step) or None, got {step!r} "
                        f"({type(step).__name__}); e.g. step={int(step)}" if str(step).isdigit() else
                        f"load_trained: step must be an int (a checkpoint's step) or None, got {step!r}")
    run = pathlib.Path(run_dir).expanduser().absolute()
    if not run.is_dir():
        raise UserError(f"{run} is not a folder: pass the output folder of a cusgs-train run "
                        "(it holds checkpoints/ and eval.json)")
    evaluation = read_eval(run)  # the run's eval.json through the run-folder contract (run_folder.py)
    cfg_file = _hydra_config(run)
    ckpt_dir = _checkpoint_dir(run, cfg_file)
    step, arrays, meta = read_arrays(ckpt_dir, ("anchors", "nets"), step=step)
    meta = CheckpointMeta.from_json(meta, f"checkpoint {ckpt_dir / str(step)}")

    try:
        stored = arrays["anchors"]
        params = stored["params"]
        anchors = AnchorState(
            centers=jnp.asarray(stored["centers"], jnp.float32), alive=jnp.asarray(stored["alive"], bool),
            params=AnchorParams(offsets=jnp.asarray(params["offsets"]), log_scaling=jnp.asarray(params["log_scaling"]),
                                latent=jnp.asarray(params["latent"]),
                                query_table=None if params.get("query_table") is None
                                else jnp.asarray(params["query_table"])))
        nets = jax.tree_util.tree_map(jnp.asarray, arrays["nets"])
        shape = _decoder_shape(anchors, nets)
    except (KeyError, TypeError, IndexError, ValueError) as e:
        raise CheckpointError(f"checkpoint {ckpt_dir / str(step)} does not hold a cusgs-jax model "
                              f"({type(e).__name__}: {e})") from e
    if not np.any(np.asarray(anchors.alive)):
        raise CheckpointError(f"checkpoint {ckpt_dir / str(step)} has no alive anchor: nothing to load")

    cfg = _config(run, cfg_file, meta, shape)
    voxel = (evaluation or {}).get("voxel_size", meta.get("voxel_size"))
    if cfg.model.voxel_size is None and voxel is not None:  # auto: the size the run resolved
        cfg = cfg.replace(model=dict(voxel_size=float(voxel)))
    world = (evaluation or {}).get("world_transform") or meta.get("world_transform")
    world = None if world is None else WorldTransform.from_dict(world)
    folder = ckpt_dir / str(step)
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    cameras, cameras_from = _train_cameras(meta, cfg, world)
    return TrainedModel(cfg=cfg, anchors=compact(anchors), nets=nets, world=world, step=int(step), run_dir=run,
                        checkpoint_dir=ckpt_dir, checkpoint_bytes=int(size), evaluation=evaluation,
                        cameras=cameras, cameras_from=cameras_from,
                        held_out_cameras=stored_cameras(meta.get("held_out_cameras")), banks=_banks(run))


# --- helpers ---------------------------------------------------------------------------------


def _hydra_config(run: pathlib.Path) -> DictConfig | None:
    """The OmegaConf of ``.hydra/config.yaml``, or None."""
    path = run / HYDRA_DIR / "config.yaml"
    if not path.is_file():
        return None
    try:
        return OmegaConf.load(path)
    except Exception as e:
        raise UserError(f"{path} cannot be read ({type(e).__name__}: {e})") from e


def _checkpoint_dir(run: pathlib.Path, cfg_file: DictConfig | None) -> pathlib.Path:
    """``<run>/checkpoints``, or the run's ``train.checkpoint_dir`` when it named another folder."""
    default = run / CHECKPOINTS_DIR
    if default.is_dir() or cfg_file is None:
        if not default.is_dir():
            raise CheckpointError(f"{run} has no checkpoints/ folder: not the output folder of a cusgs-train run "
                                  "(or it was trained with train.checkpoint_dir elsewhere)")
        return default
    other = cfg_file.get("train", {}).get("checkpoint_dir")
    if other:
        path = pathlib.Path(str(other)).expanduser()
        for candidate in ((path,) if path.is_absolute() else (run / path, path.absolute())):
            if candidate.is_dir():
                return candidate
    raise CheckpointError(f"{run} has no checkpoints/ folder{f' (train.checkpoint_dir={other})' if other else ''}: "
                          "not the output folder of a cusgs-train run with saved checkpoints")


def _decoder_shape(anchors: AnchorState, nets: dict[str, Any]) -> dict[str, Any]:
    """ModelConfig fields that fix the decoder's array shapes, read off the stored arrays."""
    decoder = nets["decoder"]
    n_offsets, latent_dim = int(anchors.params.offsets.shape[1]), int(anchors.params.latent.shape[1])
    hidden = int(decoder["opacity"]["w0"].shape[1])
    appearance = "appearance" in nets
    shape = dict(n_offsets=n_offsets, latent_dim=latent_dim, hidden=hidden, appearance=appearance)
    if appearance:
        shape["appearance_dim"] = int(nets["appearance"].shape[1])
    expected_in = latent_dim + 3 + shape.get("appearance_dim", 0)
    if decoder["color"]["w0"].shape[0] != expected_in or decoder["opacity"]["w0"].shape[0] != latent_dim + 3:
        raise ValueError(f"decoder input widths {decoder['opacity']['w0'].shape[0]}/{decoder['color']['w0'].shape[0]} "
                         f"do not fit latent {latent_dim} and appearance {shape.get('appearance_dim', 0)}")
    return shape


def _config(run: pathlib.Path, cfg_file: DictConfig | None, meta: CheckpointMeta, shape: dict[str, Any]) -> Config:
    """The run's Config (Hydra's file, else the checkpoint's record, else defaults) with the stored decoder shape."""
    source = None
    try:
        if cfg_file is not None:
            source = run / HYDRA_DIR / "config.yaml"
            cfg = from_omegaconf(cfg_file)
        elif isinstance(meta.get("config"), dict):
            source = f"the checkpoint metadata of {run}"
            cfg = from_dict(meta.get("config"))
        else:
            cfg = Config()
            log.warning("%s records no configuration (no .hydra/config.yaml): using the defaults, with the "
                        "decoder shape read off the checkpoint", run)
    except UserError as e:  # a setting the config schema refuses: name where it came from
        raise UserError(f"the configuration in {source} is refused: {e}") from e
    except Exception as e:
        raise UserError(f"the configuration in {source} cannot be read ({type(e).__name__}: {e})") from e
    differs = {k: (getattr(cfg.model, k), v) for k, v in shape.items() if getattr(cfg.model, k) != v}
    if differs and source is not None:
        log.warning("the configuration in %s does not match the checkpoint's arrays (%s); using the arrays' shape",
                    source, ", ".join(f"model.{k}={a} vs stored {b}" for k, (a, b) in differs.items()))
    return cfg.replace(model=shape) if differs else cfg


def _train_cameras(meta: CheckpointMeta, cfg: Config,
                   world: WorldTransform | None) -> tuple[Camera | None, str | None]:
    """(batched Camera of the training views in the normalised frame, where from) or (None, None)."""
    stored = meta.get("train_cameras")
    if isinstance(stored, dict):
        cameras = stored_cameras(stored)
        if cameras is not None:
            return cameras, "checkpoint"
        log.warning("the checkpoint's train_cameras cannot be read; looking for the scene instead")
    if world is None:
        return None, None
    data = cfg.data
    path = scene_folder(data.path, data, generate=False)
    if not path.is_dir():
        return None, None
    try:  # the run's scene in any layout, as the run loaded it (its cameras: no image is read)
        scene = load_cameras(path, data)
    except UserError as e:
        log.warning("the run's scene %s cannot give the training cameras (%s)", path, e)
        return None, None
    train = scene.train_indices
    viewmats = world.viewmats(scene.viewmats[train]).astype(np.float32)
    lens = None if scene.lens is None else Lens.of_views(scene.lens, train)
    return Camera(jnp.asarray(scene.Ks[train]), jnp.asarray(viewmats), scene.width, scene.height, lens), str(path)


def stored_cameras(stored: Any) -> Camera | None:
    """A batched Camera from the checkpoint metadata's {"viewmats", "Ks", "width", "height"} (and "lens":
    {"coeffs", "bounds", "fisheye"} for a ``data.undistort=lens`` run), or None."""
    if not isinstance(stored, dict):
        return None
    try:
        viewmats, Ks = np.asarray(stored["viewmats"], np.float32), np.asarray(stored["Ks"], np.float32)
        lens = stored.get("lens")
        if lens is not None:
            lens = Lens(jnp.asarray(lens["coeffs"], jnp.float32), jnp.asarray(lens["bounds"], jnp.float32),
                        bool(lens["fisheye"]))
            if lens.coeffs.shape != (len(viewmats), 6) or lens.bounds.shape != (len(viewmats), 4):
                return None
        if viewmats.ndim == 3 and viewmats.shape[1:] == (4, 4) and Ks.shape == (len(viewmats), 3, 3) and len(Ks):
            return Camera(jnp.asarray(Ks), jnp.asarray(viewmats), int(stored["width"]), int(stored["height"]), lens)
    except (KeyError, TypeError, ValueError):
        pass
    return None


def _banks(run: pathlib.Path) -> dict[str, np.ndarray] | None:
    """{model: [M, D] float32} from the run's ``feature_banks.npz``, or None when it has none."""
    path = run / BANKS_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as stored:
            return {name: np.asarray(stored[name], np.float32) for name in stored.files}
    except (OSError, ValueError) as e:
        raise CheckpointError(f"{path} cannot be read ({e}): is the run folder damaged?") from e
