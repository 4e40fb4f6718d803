"""The tiny training runs the shell's tests share (tests/app): a 30-step schedule on a 40×30 demo scene."""

from __future__ import annotations

from cusgs_jax.compose import compose_config
from cusgs_jax.config import Config

TINY = ("train.iterations=30", "train.checkpoint_every=10", "train.progress=false", "eval.every=15",
        "grow.stats_start=2", "grow.start=10", "grow.stop=30", "grow.interval=10",
        "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
        "model.voxel_size=0.06", "prune.start=10", "prune.interval=10", "prune.ratio=0.05", "train.defer_views=false")
"""Overrides of a run small enough for a test: every strategy acts within 30 steps of a tiny model. Views are not
deferred (``train.defer_views=false``): tests compare runs bit for bit, and a deferral depends on when a background
compile finishes (tests/app/test_deferral.py turns it on)."""


def tiny_config(scene, *extra: str) -> Config:
    """The :data:`TINY` run of the scene folder ``scene``, with ``extra`` overrides after them."""
    return compose_config([f"data.path={scene}", *TINY, *extra])
