"""Training from Python: ``cusgs_jax.train(config, out_dir) -> TrainResult`` — ``cusgs-train``'s run, as a function.

``cusgs-train`` (:mod:`cusgs_jax.app.train`) is one caller of :func:`train`; research code is another. The run is
the CLI's: setup → start → train → finalise (:mod:`cusgs_jax.app.run`), the same folder, the same numbers.
A loop of one's own is written from the same pieces (``docs/api.md#a-loop-of-your-own``).
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import pathlib
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from cusgs_jax.config import Config
from cusgs_jax.densify.base import Strategy
from cusgs_jax.errors import ConfigError
from cusgs_jax.io.load_run import TrainedModel, stored_cameras
from cusgs_jax.model.anchors import compact
from cusgs_jax.run_folder import EvalRecord
from cusgs_jax.training.loss_terms import LossTerm

__all__ = ["train", "TrainResult", "as_config", "LOG_FORMAT"]

log = logging.getLogger("cusgs_jax")

#: The line format of ``cusgs-train``'s console log (Hydra's default job logging), used by :func:`train`.
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"


class TrainResult(NamedTuple):
    """What :func:`train` returns: ``model, record = cusgs_jax.train(...)``.

    Attributes:
      model: the trained model as :func:`cusgs_jax.load_trained` would read it back from the folder
        (:class:`~cusgs_jax.io.load_run.TrainedModel`: compacted anchors, networks, cameras, banks, the record).
      record: the run's record, ``eval.json`` (:class:`~cusgs_jax.run_folder.EvalRecord`).
    """

    model: TrainedModel
    record: EvalRecord


def as_config(config: Config | Sequence[str] | None) -> Config:
    """The :class:`~cusgs_jax.config.Config` that ``config`` names: a Config as it is; None or a list of
    command-line overrides (``["model.voxel_size=0.02"]``) composed as ``cusgs-train`` composes them
    (:func:`cusgs_jax.compose_config`: its config groups included)."""
    if isinstance(config, Config):
        return config
    if config is None:
        config = ()
    if not isinstance(config, (list, tuple)) or not all(isinstance(item, str) for item in config):
        raise ConfigError(f"config: give a cusgs_jax.Config, a list of overrides such as ['train.iterations=500'], "
                          f"or None (the defaults), not {config!r}")
    from cusgs_jax.compose import compose_config  # Hydra's compose API (lazy: a Config needs none of it)

    return compose_config(list(config))


@contextlib.contextmanager
def console_log(enabled: bool = True):
    """While inside: the ``cusgs_jax`` log printed as ``cusgs-train`` prints it (INFO, :data:`LOG_FORMAT`), unless
    ``enabled`` is False or the caller configured logging: a handler on the ``cusgs_jax`` logger, or on the root one
    other than Python's bare ``basicConfig()`` default (which absl installs when orbax logs on import)."""
    package, root = logging.getLogger("cusgs_jax"), logging.getLogger()
    if not enabled or package.handlers or any(not _bare_default(handler) for handler in root.handlers):
        yield
        return
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    level, propagate = package.level, package.propagate
    package.addHandler(handler)
    package.propagate = False  # not twice through a bare default root handler
    if package.level == logging.NOTSET:
        package.setLevel(logging.INFO)
    quiet = {name: logging.getLogger(name).level for name in ("absl", "jax._src.xla_bridge")}
    for name in quiet:  # as cusgs-train: orbax is chatty at INFO, JAX says "no TPU"
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.setLevel(level)
        package.propagate = propagate
        for name, was in quiet.items():
            logging.getLogger(name).setLevel(was)


def _bare_default(handler: logging.Handler) -> bool:
    """Whether ``handler`` is what a bare ``logging.basicConfig()`` installs (a stream, the default format)."""
    formatter = handler.formatter
    return type(handler) is logging.StreamHandler and formatter is not None and formatter._fmt == logging.BASIC_FORMAT


def train(config: Config | Sequence[str] | None = None, out_dir=None, *, loss_terms: Sequence[LossTerm] = (),
          strategies: Sequence[Strategy] = (), log: bool = True, progress_label: str = "train",
          started: float | None = None) -> TrainResult:
    """Train, checkpoint and evaluate one run — what ``cusgs-train`` does — and return the model and its record.

    Args:
      config: a :class:`~cusgs_jax.config.Config`, a list of ``cusgs-train`` overrides
        (``["data.path=/scenes/garden", "train.iterations=3000"]``) or None (``cusgs-train``'s defaults).
      out_dir: the run folder (written as ``cusgs-train`` writes ``outputs/<date>/<time>/``: ``eval.json``,
        ``metrics.jsonl``, checkpoints, renders); None: ``outputs/<date>/<time>`` in the working directory.
      loss_terms: research code's own loss terms (:class:`~cusgs_jax.training.loss_terms.LossTerm`), added to
        the built-in ones, each logged per step in ``metrics.jsonl`` and summed in ``eval.json``'s ``loss_terms``.
      strategies: research code's own densification strategies (:class:`~cusgs_jax.densify.base.Strategy`),
        run after the configured ones. A resume (``train.resume=true``) passes the same terms and strategies.
      log: print the run's log lines as ``cusgs-train`` does when the caller has configured no logging
        (``False``, or ``logging.getLogger("cusgs_jax").setLevel(logging.WARNING)``, keeps it quiet;
        ``train.progress=false`` hides the progress bar).
      progress_label: the progress bar's label. started: the ``time.perf_counter()`` at which the process
        began (``eval.json``'s ``time`` then covers the start-up too).
    Returns:
      :class:`TrainResult` ``(model, record)``.
    Raises:
      UserError (:class:`~cusgs_jax.errors.ConfigError`, :class:`~cusgs_jax.data.errors.SceneError`, ...): a bad
      setting or input, with one line naming it and the fix (the CLI prints that line and exits 2).
    """
    from cusgs_jax.app.run import run_session  # lazy: JAX and the loop load on the first run

    cfg = as_config(config)
    out = pathlib.Path(out_dir if out_dir is not None
                       else pathlib.Path("outputs") / datetime.datetime.now().strftime("%Y-%m-%d/%H-%M-%S"))
    with console_log(log):
        session, loop, record = run_session(cfg, out, progress_label=progress_label, started=started,
                                            strategies=tuple(strategies), loss_terms=tuple(loss_terms))
    return TrainResult(trained_model(session, loop, record), record)


def trained_model(session, loop, record: EvalRecord | None = None) -> TrainedModel:
    """The :class:`~cusgs_jax.io.load_run.TrainedModel` of a run's ``session`` and ``loop`` as they are now (what
    :func:`cusgs_jax.load_trained` reads back from the run's newest checkpoint)."""
    state = loop.state
    step_folder = session.ckpt.directory / str(int(state.step))
    size = sum(f.stat().st_size for f in step_folder.rglob("*") if f.is_file()) if step_folder.is_dir() else 0
    return TrainedModel(cfg=session.cfg, anchors=compact(state.anchors), nets=dict(state.nets), world=session.world,
                        step=int(state.step), run_dir=session.out.absolute(),
                        checkpoint_dir=pathlib.Path(session.ckpt.directory).absolute(), checkpoint_bytes=int(size),
                        evaluation=record, cameras=stored_cameras(session.cameras(session.train_idx)),
                        cameras_from="checkpoint",
                        held_out_cameras=stored_cameras(session.cameras(session.scene.test_indices)),
                        banks=None if session.banks is None
                        else {name: np.asarray(bank) for name, bank in session.banks.items()})
