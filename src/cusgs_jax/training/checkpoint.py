"""Orbax checkpoints of the whole training state plus a JSON of host-side metadata.

Orbax writes each checkpoint into a temporary folder and renames it only when
complete, and the manager ignores unfinished folders, so a run killed during a
save never leaves an unreadable latest checkpoint: resuming picks the newest
finished one.

On top of that, :class:`Checkpointer` turns the failures a user can fix into one
:class:`~cusgs_jax.errors.CheckpointError` line naming the folder:

* a checkpoint folder that cannot be written (checked when constructed);
* a full disk (or any other OS error) during :meth:`Checkpointer.save`: the
  partial checkpoint is removed and orbax's own error logging is dropped;
* a finished checkpoint whose files were damaged afterwards:
  :meth:`Checkpointer.restore_latest` logs a one-line warning, moves it aside to
  ``<step>.damaged`` and falls back to the next older one;
* a template whose tree or leaf shapes differ from the stored state (the run
  folder was trained with other model settings): named leaf by leaf, with no
  fallback, since every older checkpoint would differ the same way;
* saving a step that already exists (a fresh run pointed at an old folder).

After a failed read or write orbax's abandoned threads keep reporting the same
error (absl and asyncio logs, unraisable "Event loop is closed", "coroutine was
never awaited" warnings), possibly long after the call returned. The library
leaves the process's logging, warnings and ``sys.unraisablehook`` alone; an
application that wants that noise gone enters :func:`quiet_orbax` around its
work (``cusgs-train`` does), which installs a narrow filter (:class:`_Aftermath`)
until it exits.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import shutil
import tempfile
import time
from typing import Callable

import jax
import numpy as np
import orbax.checkpoint as ocp

from cusgs_jax.errors import CheckpointError
from cusgs_jax.training.orbax_noise import _AFTERMATH, _DISK_FULL, _OrbaxLogCapture, _os_error
from cusgs_jax.training.orbax_noise import quiet_orbax  # noqa: F401  (re-exported: the app enters it)

log = logging.getLogger("cusgs_jax")

_TMP_SUFFIX = ".orbax-checkpoint-tmp"
_DAMAGED_SUFFIX = ".damaged"
_NEW_RUN = "start a new run in a fresh folder (hydra.run.dir=...)"


class Checkpointer:
    """Save/restore ``(state pytree, metadata dict)`` pairs under ``directory``."""

    def __init__(self, directory: str | pathlib.Path, max_to_keep: int = 2):
        self.directory = pathlib.Path(directory).absolute()
        self.max_to_keep = max_to_keep
        _check_writable(self.directory)
        self.manager = self._new_manager()

    def _new_manager(self) -> ocp.CheckpointManager:
        try:
            return ocp.CheckpointManager(
                self.directory,
                options=ocp.CheckpointManagerOptions(max_to_keep=self.max_to_keep, create=True),
                # named handlers let item_metadata() read a stored tree before any save in this process
                item_handlers=dict(state=ocp.StandardCheckpointHandler(), meta=ocp.JsonCheckpointHandler()),
            )
        except OSError as e:
            raise _unwritable(self.directory, e) from e

    # --- queries -----------------------------------------------------------------------------

    def latest_step(self) -> int | None:
        """Newest finished checkpoint (possibly damaged; :meth:`restore_latest` checks)."""
        return self.manager.latest_step()

    def steps(self) -> list[int]:
        """Finished checkpoints, newest first."""
        return sorted(self.manager.all_steps(), reverse=True)

    def folder(self, step: int) -> pathlib.Path:
        return self.directory / str(step)

    def step_bytes(self, step: int | None = None) -> int:
        """Bytes on disk of one checkpoint."""
        step = self.latest_step() if step is None else step
        return sum(f.stat().st_size for f in self.folder(step).rglob("*") if f.is_file())

    # --- save --------------------------------------------------------------------------------

    def save(self, step: int, state, metadata: dict) -> None:
        """Save and wait until the checkpoint is finalised on disk.

        An OS error (disk full, permission denied, ...) removes the partial
        checkpoint and raises :class:`CheckpointError`; the previous checkpoints
        are untouched.
        """
        if step in self.manager.all_steps():
            raise CheckpointError(f"checkpoint {step} already exists in {self.directory}: resume with "
                                  f"train.resume=true, or {_NEW_RUN}")
        existed = self.folder(step).exists()
        with _OrbaxLogCapture() as orbax_log:
            try:
                self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                                meta=ocp.args.JsonSave(metadata)), force=True)
                self.manager.wait_until_finished()
            except Exception as e:
                os_error = _os_error(e)
                if os_error is not None:
                    _AFTERMATH.mute(f"{self.directory / str(step)}{_TMP_SUFFIX}")
                self._discard_partial(step, existed)
                if os_error is None:
                    orbax_log.replay()
                    raise
                raise self._save_error(step, *os_error) from e
            orbax_log.replay()

    def _discard_partial(self, step: int, existed: bool) -> None:
        """Remove what a failed save of ``step`` left and reopen the manager on what is on disk."""
        with contextlib.suppress(Exception):
            self.manager.close()
        # writes still in flight when orbax gave up may land after a first removal: repeat until none appear
        for _ in range(20):
            leftovers = list(self.directory.glob(f"{step}{_TMP_SUFFIX}*"))
            for tmp in leftovers:
                shutil.rmtree(tmp, ignore_errors=True)
            time.sleep(0.05)
            if not leftovers and not list(self.directory.glob(f"{step}{_TMP_SUFFIX}*")):
                break
        self.manager = self._new_manager()
        final = self.folder(step)
        if not existed and final.exists() and step not in self.manager.all_steps():
            shutil.rmtree(final, ignore_errors=True)  # not finalised: orbax would not list it
            self.manager.reload()

    def _save_error(self, step: int, code: int | None, reason: str) -> CheckpointError:
        last = self.latest_step()
        last = ("there is no complete checkpoint yet" if last is None
                else f"the last complete checkpoint is {last} (resume with train.resume=true)")
        if code in _DISK_FULL:
            return CheckpointError(f"{_DISK_FULL[code]} while writing checkpoint {step} into {self.directory}: "
                                   f"free space or point train.checkpoint_dir at a disk with room; {last}")
        return CheckpointError(f"cannot write checkpoint {step} into {self.directory} ({reason}): set "
                               f"train.checkpoint_dir (or hydra.run.dir) to a writable folder; {last}")

    # --- restore -----------------------------------------------------------------------------

    def metadata(self, step: int | None = None) -> dict:
        """The metadata dict of ``step``, or of the newest checkpoint whose metadata reads cleanly.

        Prefer :meth:`restore_latest`, which also checks the state arrays of the
        checkpoint it picks.
        """
        if step is not None:
            try:
                return self._read_meta(step)
            except Exception as e:
                raise self._unreadable(step, e) from e
        failures = []
        for step in self.steps():
            try:
                return self._read_meta(step)
            except Exception as e:
                failures.append((step, e))
                self._warn_damaged(step, e)
        raise self._none_restores(failures)

    def restore(self, template, step: int | None = None):
        """Restore ``(state, metadata)``; ``template`` gives the pytree structure and shapes.

        Without ``step``, the newest checkpoint that restores cleanly (see :meth:`restore_latest`).
        """
        if step is None:
            return self.restore_latest(lambda meta: template)
        try:
            return self._restore_step(step, lambda meta: template)
        except _Damaged as e:
            raise self._unreadable(step, e.__cause__) from e.__cause__

    def restore_latest(self, make_template: Callable[[dict], object]):
        """Restore ``(state, metadata)`` from the newest checkpoint that restores cleanly.

        ``make_template(metadata)`` gives the pytree structure and shapes for that
        checkpoint (e.g. padded to its stored capacity). Each damaged checkpoint
        met on the way is logged as a warning and moved aside to
        ``<step>.damaged`` once an older one restored, so later saves can reuse
        its step. Raises :class:`CheckpointError` if none restores, or if the
        stored tree or shapes differ from the template (no fallback then).
        """
        failures = []
        for step in self.steps():
            try:
                state, meta = self._restore_step(step, make_template)
            except _Damaged as e:
                failures.append((step, e.__cause__))
                self._warn_damaged(step, e.__cause__)
                continue
            for bad, _ in failures:
                self._move_aside(bad)
            if failures:
                self.manager.reload()
            return state, meta
        raise self._none_restores(failures)

    def _read_meta(self, step: int) -> dict:
        meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        if not isinstance(meta, dict):
            raise ValueError(f"metadata is a {type(meta).__name__}, not a dict")
        return meta

    def _restore_step(self, step: int, make_template):
        """Restore one step; damage is raised as :class:`_Damaged` (its cause the orbax error)."""
        with _OrbaxLogCapture() as orbax_log:
            try:
                meta = self._read_meta(step)
            except Exception as e:
                raise _Damaged() from e
            template = make_template(meta)
            try:
                stored = self.manager.item_metadata(step)["state"]
                if stored is None:
                    raise ValueError('no "state" item')
            except Exception as e:
                raise _Damaged() from e
            self._check_shapes(step, stored, template)
            abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, template)
            try:
                state = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
            except Exception as e:
                _AFTERMATH.mute(f"{self.folder(step)}{os.sep}")
                raise _Damaged() from e
            orbax_log.replay()
        return state["state"], meta

    def _check_shapes(self, step: int, stored, template) -> None:
        """Raise :class:`CheckpointError` naming the leaves whose presence or shape differ."""
        have = {_dotted(path): tuple(getattr(leaf, "shape", ()) or ())
                for path, leaf in jax.tree_util.tree_leaves_with_path(stored)}
        want = {_dotted(path): tuple(np.shape(leaf))
                for path, leaf in jax.tree_util.tree_leaves_with_path(template)}
        diffs = []
        for name in list(want) + [n for n in have if n not in want]:
            if name not in have:
                diffs.append(f"{name} missing from the checkpoint, expected {want[name]}")
            elif name not in want:
                diffs.append(f"{name} stored {have[name]}, not in this model")
            elif have[name] != want[name]:
                diffs.append(f"{name} stored {have[name]}, expected {want[name]}")
        if not diffs:
            return
        more = f" (and {len(diffs) - 3} more)" if len(diffs) > 3 else ""
        raise CheckpointError(
            f"checkpoint {self.folder(step)} does not fit this model: {'; '.join(diffs[:3])}{more}. This run folder "
            f"was trained with different model settings: resume with the original settings, or {_NEW_RUN}")

    def _warn_damaged(self, step: int, error: BaseException) -> None:
        older = [s for s in self.steps() if s < step]
        then = f"trying checkpoint {older[0]}" if older else "no older checkpoint to try"
        log.warning("checkpoint %s cannot be restored (%s); %s", self.folder(step), _one_line(error), then)

    def _move_aside(self, step: int) -> None:
        """Rename a damaged checkpoint out of orbax's sight (orbax only lists all-digit folders)."""
        folder = self.folder(step)
        target, n = folder.with_name(folder.name + _DAMAGED_SUFFIX), 1
        while target.exists():
            n += 1
            target = folder.with_name(f"{folder.name}{_DAMAGED_SUFFIX}{n}")
        try:
            folder.rename(target)
            log.warning("moved damaged checkpoint %s aside to %s", folder, target.name)
        except OSError as e:
            log.warning("could not move damaged checkpoint %s aside (%s)", folder, _one_line(e))

    def _unreadable(self, step: int, error: BaseException) -> CheckpointError:
        return CheckpointError(f"checkpoint {self.folder(step)} cannot be restored ({_one_line(error)}): it is "
                               f"damaged; restore another step, or {_NEW_RUN}")

    def _none_restores(self, failures) -> CheckpointError:
        if not failures:
            return CheckpointError(f"no checkpoint in {self.directory} to restore: check train.checkpoint_dir, "
                                   f"or {_NEW_RUN} without train.resume=true")
        tried = "; ".join(f"{step}: {_one_line(e, 160)}" for step, e in failures)
        return CheckpointError(f"no checkpoint in {self.directory} can be restored (tried {tried}): they are damaged; "
                               f"{_NEW_RUN}")

    def close(self) -> None:
        """Wait for orbax's background work and stop it (idempotent)."""
        if not getattr(self, "_closed", False):
            self._closed = True
            self.manager.close()

    def close_after_error(self) -> None:
        """:meth:`close` on an error path (e.g. a full disk): orbax's threads stop before the interpreter does,
        so they cannot print a traceback at exit; a second failure while closing is logged, not raised."""
        try:
            self.close()
        except Exception as e:  # noqa: BLE001 - the error being raised is the one to report
            log.debug("closing the checkpointer after an error failed too: %s", e)


def read_arrays(directory: str | pathlib.Path, keys: tuple[str, ...] = ("anchors", "nets"),
                step: int | None = None) -> tuple[int, dict, dict]:
    """Read part of a stored state without a template and without writing anything.

    Opens the checkpoints read-only (nothing is created, moved or removed, so a
    run folder on a read-only disk works) and restores only the top-level
    ``keys`` of the state tree — e.g. anchors and networks, not the optimiser
    moments — as nested dicts of NumPy arrays in the stored layout (dataclass
    pytrees come back as dicts keyed by field name; a ``None`` field stays None).

    Args:
      directory: the checkpoint folder (``<run>/checkpoints``).
      keys: top-level entries of the state tree to read.
      step: a given step; None: the newest one that reads cleanly (a damaged
        newer one is skipped with a warning, as :meth:`Checkpointer.restore_latest`).
    Returns:
      (step, {key: nested dict of np.ndarray}, metadata dict).
    Raises:
      CheckpointError: no checkpoint there, the step is missing, none reads,
        or a key is not in the stored tree (folder named).
    """
    directory = pathlib.Path(directory).absolute()
    if not directory.is_dir():
        raise CheckpointError(f"no checkpoint folder {directory}: expected the checkpoints/ of a cusgs-train run")
    with _OrbaxLogCapture():  # orbax warns that a read-only manager saves nothing: dropped
        manager = ocp.CheckpointManager(
            directory, options=ocp.CheckpointManagerOptions(create=False, read_only=True),
            item_handlers=dict(state=ocp.PyTreeCheckpointHandler(), meta=ocp.JsonCheckpointHandler()))
    try:
        steps = sorted(manager.all_steps(), reverse=True)
        if step is not None:
            if step not in steps:
                have = ", ".join(map(str, steps)) or "none"
                raise CheckpointError(f"no checkpoint {step} in {directory} (steps there: {have})")
            steps = [step]
        failures = []
        for candidate in steps:
            try:
                arrays, meta = _read_arrays_step(manager, candidate, keys, directory)
            except _Damaged as e:
                if step is not None:
                    raise CheckpointError(f"checkpoint {directory / str(candidate)} cannot be read "
                                          f"({_one_line(e.__cause__)}): it is damaged") from e.__cause__
                failures.append((candidate, e.__cause__))
                older = [s for s in steps if s < candidate]
                log.warning("checkpoint %s cannot be read (%s); %s", directory / str(candidate),
                            _one_line(e.__cause__), f"trying checkpoint {older[0]}" if older else "none older")
                continue
            return candidate, arrays, meta
        if not failures:
            raise CheckpointError(f"no checkpoint in {directory}: the run saved none (train.checkpoint_every=0 "
                                  "and it did not finish?)")
        tried = "; ".join(f"{s}: {_one_line(e, 160)}" for s, e in failures)
        raise CheckpointError(f"no checkpoint in {directory} can be read (tried {tried}): they are damaged")
    finally:
        with contextlib.suppress(Exception):
            manager.close()


def _read_arrays_step(manager, step: int, keys, directory: pathlib.Path) -> tuple[dict, dict]:
    """One step of :func:`read_arrays`; damage raised as :class:`_Damaged`, a missing key as CheckpointError."""
    with _OrbaxLogCapture():
        try:
            meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
            stored = manager.item_metadata(step)["state"]
            stored = getattr(stored, "tree", stored)
            if not isinstance(stored, dict):
                raise ValueError('no "state" item')
        except Exception as e:
            raise _Damaged() from e
        missing = [k for k in keys if k not in stored]
        if missing:
            raise CheckpointError(f"checkpoint {directory / str(step)} has no {', '.join(missing)} in its state "
                                  f"(it holds {', '.join(sorted(stored))}): not a cusgs-train checkpoint")
        item = {k: jax.tree_util.tree_map(lambda m: jax.ShapeDtypeStruct(tuple(m.shape), m.dtype), stored[k])
                for k in keys}
        restore_args = jax.tree_util.tree_map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), item)
        try:
            state = manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.PyTreeRestore(item, restore_args=restore_args, partial_restore=True)))["state"]
        except Exception as e:
            _AFTERMATH.mute(f"{directory / str(step)}{os.sep}")
            raise _Damaged() from e
    return {k: state[k] for k in keys}, dict(meta or {})


class _Damaged(Exception):
    """Internal: one checkpoint failed to read (its ``__cause__`` says why)."""


# --- helpers ---------------------------------------------------------------------------------


def _check_writable(directory: pathlib.Path) -> None:
    """Create ``directory`` and write a probe file in it, or raise :class:`CheckpointError`."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise _unwritable(directory, e) from e


def _unwritable(directory: pathlib.Path, error: OSError) -> CheckpointError:
    reason = error.strerror or str(error)
    if error.filename and str(error.filename) != str(directory):
        reason += f": {error.filename}"
    return CheckpointError(f"checkpoint folder {directory} is not writable ({reason}): set train.checkpoint_dir "
                           f"or hydra.run.dir to a writable folder")


def _dotted(path) -> str:
    """``anchors.params.latent`` for a key path (orbax's own naming of stored leaves)."""
    parts = []
    for key in path:
        for attr in ("key", "name", "idx"):
            if hasattr(key, attr):
                parts.append(str(getattr(key, attr)))
                break
        else:
            parts.append(str(key))
    return ".".join(parts)


def _one_line(error: BaseException | None, limit: int = 300) -> str:
    """``Type: first line`` of the innermost explicit cause of ``error``, at most ``limit`` characters."""
    while error is not None and error.__cause__ is not None:
        error = error.__cause__
    if error is None:
        return "unknown error"
    text = str(error).strip().splitlines()
    text = f"{type(error).__name__}: {text[0] if text else ''}".rstrip(": ")
    return text if len(text) <= limit else text[:limit - 3] + "..."
