"""Resuming a run (``train.resume=true``): the newest checkpoint restored, checked against the run at hand.

A resumed run continues the same run: on the scene it trained on (its recorded training cameras,
:func:`require_same_scene`), never backwards (setup refuses a checkpoint past ``train.iterations``,
:func:`cusgs_jax.app.session.require_not_past`, and a restored one is never newer), with its logs trimmed to the
restored step so every step stays logged once (:func:`trim_jsonl`).
"""

from __future__ import annotations

import json
import logging
import pathlib

import numpy as np

from cusgs_jax.app.deferral import ViewQueue
from cusgs_jax.config import require
from cusgs_jax.data.identity import same_cameras
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import Tally
from cusgs_jax.run_folder import CURVE_FILE, METRICS_FILE, CheckpointMeta
from cusgs_jax.training.loss_terms import LossTally

log = logging.getLogger("cusgs_jax")


def resume(session, loop) -> None:
    """Restore the newest checkpoint of ``session`` (:class:`cusgs_jax.app.session.Session`) that restores cleanly
    into its ``loop`` (:class:`~cusgs_jax.app.loop.Loop`: state, capacities, curve, tallies, counts) and its
    budget's clock, and trim the logs to its step."""
    def template(meta: dict):
        fresh, saved = loop.state, int(meta["capacity"])
        if saved == fresh.anchors.capacity:
            return fresh
        if saved > fresh.anchors.capacity:
            return ops.grow_capacity(fresh, loop.tx, saved)
        return ops.resize_capacity(fresh, loop.tx, saved, keep=np.arange(saved))  # shapes only: restored over

    loop.state, meta = session.ckpt.restore_latest(template)  # a damaged newest one falls back, with a warning
    step = int(loop.state.step)
    meta = CheckpointMeta.from_json(meta, f"checkpoint {session.ckpt.directory / str(step)}")  # run_folder.py
    require_same_scene(session, meta, step)
    loop.capacities = loop.capacities.restored(meta.capacities)
    session.budget.resume_clock(meta.wall_s)
    loop.curve = list(meta.curve)
    loop.tallies.update({name: Tally.from_dict(record) for name, record in (meta.densify or {}).items()})
    if meta.densify is None and "prune" in meta.extra:  # written before the strategies kept tallies
        log.warning("the checkpoint of step %d predates per-strategy tallies: the densification counts (prune "
                    "passes, pruned anchors, render_ms_before_prune) restart from zero", step)
    loop.recompilations = int(meta.recompilations or 0)
    loop.replays = int(meta.replays or 0)
    loop.loss_tally = LossTally.restored(meta.loss_terms)
    loop.views = ViewQueue.restored(meta.views, step, session.cfg.train.iterations)  # deferred views train after it
    trim_jsonl(session.out / METRICS_FILE, step)
    trim_jsonl(session.out / CURVE_FILE, step)
    log.info("resumed from step %d (capacity %d)", step, loop.state.anchors.capacity)


def require_same_scene(session, meta: CheckpointMeta, step: int) -> None:
    """A resumed run continues on the scene it was trained on: refuse another one (its recorded training
    cameras, :func:`cusgs_jax.data.identity.same_cameras`), even one with as many views."""
    recorded = meta.train_cameras
    if not recorded:  # a checkpoint written before the cameras were recorded: nothing to compare
        return
    scene, idx = session.scene, session.train_idx
    differs = same_cameras(recorded, scene.viewmats[idx], scene.Ks[idx], scene.width, scene.height)
    if differs is None:
        return
    trained_on = (meta.config or {}).get("data", {}).get("path") or "the built-in demo scene"
    require(False, "data.path", session.cfg.data.path or "the built-in demo scene",
            f"is not the scene the checkpoint of step {step} in {session.ckpt.directory} was trained on "
            f"({trained_on}): its cameras differ ({differs})",
            "resume with the run's own scene and settings, or train this scene in a new folder (hydra.run.dir=...)")


def trim_jsonl(path: pathlib.Path, last_step: int) -> None:
    """Keep the rows of ``path`` with ``step ≤ last_step`` (rows written after the checkpoint go)."""
    if not path.is_file():
        return
    rows = [line for line in path.read_text().splitlines() if line.strip()]
    kept = [line for line in rows if json.loads(line)["step"] <= last_step]
    path.write_text("".join(line + "\n" for line in kept))
