"""Orbax checkpoints of the whole training state plus a JSON of host-side metadata.

Orbax writes each checkpoint into a temporary folder and renames it only when
complete, and the manager ignores unfinished folders, so a run killed during a
save never leaves an unreadable latest checkpoint: resuming picks the newest
finished one.
"""

from __future__ import annotations

import pathlib

import jax
import orbax.checkpoint as ocp


class Checkpointer:
    """Save/restore ``(state pytree, metadata dict)`` pairs under ``directory``."""

    def __init__(self, directory: str | pathlib.Path, max_to_keep: int = 2):
        self.directory = pathlib.Path(directory).absolute()
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True),
        )

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def save(self, step: int, state, metadata: dict) -> None:
        """Save and wait until the checkpoint is finalised on disk."""
        self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                        meta=ocp.args.JsonSave(metadata)), force=True)
        self.manager.wait_until_finished()

    def metadata(self, step: int | None = None) -> dict:
        step = self.latest_step() if step is None else step
        return self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]

    def restore(self, template, step: int | None = None):
        """Restore ``(state, metadata)``; ``template`` gives the pytree structure and shapes."""
        step = self.latest_step() if step is None else step
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
        out = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                                 meta=ocp.args.JsonRestore()))
        return out["state"], out["meta"]

    def step_bytes(self, step: int | None = None) -> int:
        """Bytes on disk of one checkpoint."""
        step = self.latest_step() if step is None else step
        folder = self.directory / str(step)
        return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())

    def close(self) -> None:
        self.manager.close()
