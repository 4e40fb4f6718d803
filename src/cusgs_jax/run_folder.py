"""The run folder's contract: every file a run writes, and its two records, typed and versioned.

A run folder (``outputs/<date>/<time>/``, or a sweep job's) holds:

=========================  ==============================================================================
``eval.json``              :class:`EvalRecord`: held-out metrics, size, time budget, compilations, protocol
``metrics.jsonl``          the training log, one row per ``train.log_every`` steps
``eval_curve.jsonl``       held-out PSNR (and feature errors) every ``eval.every`` steps
``error_vs_time.png``      that curve against the training clock
``renders/``, ``features/``  held-out renders and feature maps (PNG); ``features.md`` the feature metrics
``checkpoints/``           orbax checkpoints, each with a :class:`CheckpointMeta` as its JSON metadata
``feature_banks.npz``      the PSC banks of the feature models, for renderers without the scene
``failed.json``            a sweep job that raised: its error and traceback
=========================  ==============================================================================

The trainer writes the records through :func:`write_eval` and :meth:`CheckpointMeta.to_json`; the
readers (``cusgs-report``, ``load_trained`` and through it ``cusgs-export`` and ``cusgs-view``) read
them through :func:`read_eval` and :meth:`CheckpointMeta.from_json`. Both records carry
``version`` (:data:`VERSION`). A record without one was written before the contract (version 1, up
to revision 7f1a80c): it reads, its newer fields None. A record of a newer version is refused with
one line naming both versions. A current-version record holds its fields and nothing else: a key
the record does not define (a misspelling, a hand edit) is refused naming it; records of older
versions keep such keys in ``extra`` (version 2 wrote a strategy's own keys at the top level).
``eval.json``'s ``time`` (the run's seconds per stage) is held by every record from version 2 on, its
entries numbers of seconds >= 0: a missing or negative one is refused naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import shutil
from typing import Any

from cusgs_jax.errors import UserError
from cusgs_jax.atomic import atomic_path

__all__ = ["VERSION", "EVAL_FILE", "METRICS_FILE", "CURVE_FILE", "PLOT_FILE", "RENDERS_DIR", "FEATURES_DIR",
           "FEATURES_MD", "CHECKPOINTS_DIR", "BANKS_FILE", "FAILED_FILE", "HYDRA_DIR", "HYDRA_FILES", "EvalRecord",
           "CheckpointMeta", "accept_hydra_record", "read_eval", "restore_hydra_record", "write_eval"]

#: The run-folder version this code writes; it reads every version up to it (1: unversioned records;
#: 3: every key typed, a research strategy's own ``eval.json`` keys under ``strategies``; 4: ``loss_terms`` and
#: ``appearance``).
VERSION = 4

EVAL_FILE = "eval.json"
METRICS_FILE = "metrics.jsonl"
CURVE_FILE = "eval_curve.jsonl"
PLOT_FILE = "error_vs_time.png"
RENDERS_DIR = "renders"
FEATURES_DIR = "features"
FEATURES_MD = "features.md"
CHECKPOINTS_DIR = "checkpoints"
BANKS_FILE = "feature_banks.npz"
FAILED_FILE = "failed.json"
HYDRA_DIR = ".hydra"  # Hydra's record of the job: config, its own settings, the command-line overrides
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")
_ACCEPTED = "accepted"  # HYDRA_DIR/accepted/: the record of the run the folder holds


def accept_hydra_record(out: pathlib.Path) -> None:
    """Keep a copy of the folder's Hydra record (``.hydra/accepted/``) once setup has accepted its run.

    Hydra writes ``.hydra/*.yaml`` before the run starts, also for a run that setup then refuses (a
    resume on another scene, a fresh run in a folder with checkpoints): :func:`restore_hydra_record`
    puts the accepted run's record back, so the folder never describes a run that did not happen.
    Nothing to do outside Hydra (no ``.hydra``)."""
    record = pathlib.Path(out) / HYDRA_DIR
    if not record.is_dir():
        return
    (record / _ACCEPTED).mkdir(exist_ok=True)
    _copy_record(record, record / _ACCEPTED)


def restore_hydra_record(out: pathlib.Path) -> bool:
    """Put the accepted run's Hydra record back over a refused run's (:func:`accept_hydra_record`); True
    when there was one to restore."""
    record = pathlib.Path(out) / HYDRA_DIR
    if not (record / _ACCEPTED).is_dir():
        return False
    _copy_record(record / _ACCEPTED, record)
    return True


def _copy_record(source: pathlib.Path, target: pathlib.Path) -> None:
    """Copy the :data:`HYDRA_FILES` ``source`` holds into ``target``, each file atomically."""
    for name in HYDRA_FILES:
        if (source / name).is_file():
            with atomic_path(target / name) as tmp:
                shutil.copyfile(source / name, tmp)


def _version(data: dict, where: str) -> int:
    version = data.get("version", 1)
    if not isinstance(version, int) or version < 1:
        raise UserError(f"{where}: version {version!r} is not a run-folder version (whole numbers from 1)")
    if version > VERSION:
        raise UserError(f"{where} was written by a newer cusgs-jax (run-folder version {version}; this one reads "
                        f"versions 1-{VERSION}): upgrade cusgs-jax to read it")
    return version


class _Record:
    """What both records share: read from and written to a JSON object with their fields typed, checked for
    their version. A current-version record may hold its fields only; an older one keeps the keys it does not
    know in ``extra`` (written back flat beside the fields)."""

    _what = "a run-folder record"  # how a message names the kind of record

    @classmethod
    def _names(cls) -> set[str]:
        return {f.name for f in dataclasses.fields(cls)} - {"extra"}

    @classmethod
    def from_json(cls, data: dict, where: str):
        """The record of a parsed JSON object (``where`` names it in messages); UserError for a newer version
        or, in a current-version record, a key the record does not define. Every field may be absent (None):
        an unfinished or older record still reads."""
        if not isinstance(data, dict):
            raise UserError(f"{where} holds {type(data).__name__}, not {cls._what} (a JSON object)")
        version = _version(data, where)
        names = cls._names()
        known = {k: v for k, v in data.items() if k in names}
        extra = {k: v for k, v in data.items() if k not in names}
        if extra and version == VERSION:
            unknown = ", ".join(repr(k) for k in sorted(extra))
            raise UserError(f"{where}: {unknown} {'is not a key' if len(extra) == 1 else 'are not keys'} of "
                            f"{cls._what} (run-folder version {VERSION}; its keys are {', '.join(sorted(names))}): "
                            "the file was edited or written by other code; restore it or rerun the job")
        return cls(**{**known, "version": version}, extra=extra)

    def to_json(self) -> dict:
        """The JSON object: the fields in their order, then ``extra`` flat beside them."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "extra"}
        return {**fields, **self.extra}

    def get(self, key: str, default=None):
        """A field (None counts as absent) or an ``extra`` key, by name."""
        if key in self._names():
            value = getattr(self, key)
            return default if value is None else value
        return self.extra.get(key, default)


@dataclasses.dataclass(frozen=True)
class EvalRecord(_Record):
    """``eval.json``: every key a run writes, typed. Fields an older record lacks are None (a version-2
    record keeps the keys it held beyond these in ``extra``); the optional parts' keys are None when the
    part did not run (``lpips_vgg`` / ``lpips_alex`` without the ``lpips`` extra, ``features`` without
    feature models, ``render_ms_before_prune`` without feature-aware pruning)."""

    psnr: float | None = None
    ssim: float | None = None
    per_view: list | None = None
    params: Any | None = None
    alive_anchors: int | None = None
    capacity: int | None = None
    model_bytes: int | None = None
    checkpoint_bytes: int | None = None
    train_wall_s: float | None = None
    render_ms_per_view: float | None = None
    iterations: int | None = None
    width: int | None = None
    height: int | None = None
    held_out_views: int | None = None
    evaluated_on: str | None = None
    dataset_format: str | None = None
    split: str | None = None
    background: list | None = None
    curve: list = dataclasses.field(default_factory=list)
    skipped_updates: int = 0
    dropped_anchors: int = 0
    dropped_gaussians: int = 0
    dropped_pairs: int = 0
    replayed_steps: int = 0
    recompilations: int = 0
    capacities: dict | None = None
    voxel_size: float | None = None
    world_transform: dict | None = None
    batch_size: int = 1
    devices: int = 1
    camera_frame: str | None = None
    initial_points: str | None = None
    valid_pixels: float | None = None
    # version 2
    curve_clock: str | None = None
    scene_digest: str | None = None
    accelerator: dict | None = None
    compilations: dict | None = None
    time: dict | None = None
    carving: dict | None = None  # what carving did to random initial points (data/carve.py), None otherwise
    # written flat by version 2 too (kept in its ``extra`` there)
    lpips_vgg: float | None = None
    lpips_alex: float | None = None
    features: dict | None = None  # the feature metrics of each model (eval/features.py) and their markdown
    render_ms_before_prune: float | None = None
    prune: dict | None = None  # cfg.prune and what its passes did (densify/base.run_defaults)
    densify: dict | None = None  # {strategy name: tally} (densify/base.Tally)
    # version 3
    strategies: dict | None = None  # keys a research strategy's ``results`` adds that are none of these fields
    # version 4
    loss_terms: dict | None = None  # every weighted loss term summed over the steps (training/loss_terms.py)
    appearance: str | None = None  # the held-out protocol's appearance embedding (render.py's ``appearance``)
    deferred: dict | None = None  # views trained later because their program was late (app/deferral.py)
    version: int = VERSION
    extra: dict = dataclasses.field(default_factory=dict)

    _what = "the run's record"

    @classmethod
    def from_json(cls, data: dict, where: str = EVAL_FILE) -> EvalRecord:
        """The record of a parsed ``eval.json`` (see :meth:`_Record.from_json`); its ``time`` is checked too
        (:func:`_check_time`): a record of version 2 or later holds it, each entry seconds >= 0."""
        record = super().from_json(data, where)
        _check_time(record.time, record.version, where)
        return record


#: The run-folder version from which ``eval.json`` holds ``time`` (its time budget, app/budget.py).
TIME_SINCE = 2


def _check_time(time, version: int, where: str) -> None:
    """``eval.json``'s ``time``: absent only in a record older than :data:`TIME_SINCE`; else a JSON object whose
    entries are seconds, finite and >= 0 (``compile`` may be null: compiles not told apart). UserError naming the
    file and the key otherwise (a report would show a negative or missing time as if measured)."""
    fix = "the file was edited or written by other code; restore it or rerun the job"
    if time is None:
        if version >= TIME_SINCE:
            raise UserError(f"{where}: 'time' is missing (run-folder version {version} records hold the run's time "
                            f"budget from version {TIME_SINCE} on): {fix}")
        return
    if not isinstance(time, dict):
        raise UserError(f"{where}: time={time!r} is not a JSON object of seconds per stage: {fix}")
    for key, seconds in time.items():
        if seconds is None and key == "compile":
            continue
        number = isinstance(seconds, (int, float)) and not isinstance(seconds, bool)
        if not (number and math.isfinite(seconds) and seconds >= 0):
            raise UserError(f"{where}: time.{key}={seconds!r} is not a number of seconds >= 0: {fix}")


def read_eval(folder: str | os.PathLike) -> EvalRecord | None:
    """The run's :class:`EvalRecord`, or None when the run has not finished (no ``eval.json``).

    Raises:
      UserError: an unreadable or newer ``eval.json``, naming the file.
    """
    path = pathlib.Path(folder) / EVAL_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"{path} cannot be read ({type(e).__name__}: {e}): the run's record is damaged") from e
    return EvalRecord.from_json(data, str(path))


def write_eval(folder: str | os.PathLike, record: EvalRecord) -> pathlib.Path:
    """Write ``eval.json`` whole (:func:`cusgs_jax.atomic.atomic_path`); returns its path."""
    path = pathlib.Path(folder) / EVAL_FILE
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record.to_json(), indent=1))
    return path


@dataclasses.dataclass(frozen=True)
class CheckpointMeta(_Record):
    """A checkpoint's JSON metadata: what resuming, ``cusgs-export`` and ``cusgs-view`` need besides the arrays.

    ``config`` is the run's configuration as a dict; ``train_cameras`` / ``held_out_cameras`` are
    ``{"viewmats", "Ks", "width", "height"[, "lens"]}`` in the normalised frame. Fields a version-1
    record lacks are None; keys this version does not know are kept in ``extra``.
    """

    step: int | None = None
    capacity: int | None = None
    wall_s: float | None = None
    curve: list = dataclasses.field(default_factory=list)
    densify: dict | None = None
    recompilations: int = 0
    replays: int = 0
    capacities: dict | None = None
    voxel_size: float | None = None
    world_transform: dict | None = None
    config: dict | None = None
    train_cameras: dict | None = None
    held_out_cameras: dict | None = None
    # version 2
    scene_digest: str | None = None
    # version 4
    loss_terms: dict | None = None  # LossTally.as_dict() at the checkpoint's step
    views: dict | None = None  # the batch positions still to train (app/deferral.ViewQueue.as_dict); None: all < step
    version: int = VERSION
    extra: dict = dataclasses.field(default_factory=dict)

    _what = "a checkpoint's metadata"

    @classmethod
    def from_json(cls, data: dict, where: str = "checkpoint metadata") -> CheckpointMeta:
        return super().from_json(data, where)
