"""Views over devices: the mesh, the shardings and the placement of a step's inputs.

A step on B views (``train.batch_size``) shards its views over a 1-D device mesh with
axis ``"views"``; the parameters, optimiser state and statistics are replicated, so the
update is one update, the same on every device (docs/scaling.md#sharding-over-devices: data
parallelism as gsplat's ``batch_size`` × ``world_size``). Each device renders B/D views, the
gradients are summed over the mesh (``lax.psum``) and averaged once.

Several hosts: ``jax.devices()`` then lists every process's devices and the mesh spans
them; :func:`place` builds global arrays from the same host data on every process
(every process loads the whole scene), see :mod:`cusgs_jax.training.distributed`.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cusgs_jax.config import Config, require

SHARED_INPUTS = ("banks", "loss_weights", "seed_key", "learning_rates")
"""Batch entries every view of a step shares (no view axis with B > 1; replicated over a mesh)."""

AXIS = "views"


def resolve_devices(batch_size: int, devices: str | int = "auto", available: int | None = None) -> int:
    """How many devices D the B views are sharded over.

    ``"auto"``: the largest D ≤ the devices present that divides B (1 device for B = 1).
    A number: that many, refused (:class:`~cusgs_jax.errors.ConfigError`) when more than
    are present or when it does not divide B.
    """
    available = jax.device_count() if available is None else available
    if str(devices) == "auto":
        return max(d for d in range(1, min(available, batch_size) + 1) if batch_size % d == 0)
    count = int(devices)
    require(count <= available, "train.devices", devices, f"only {available} device(s) are present",
            "use train.devices=auto (on CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N makes N)")
    require(batch_size % count == 0, "train.devices", devices, f"must divide train.batch_size={batch_size}",
            "use train.devices=auto")
    return count


def view_mesh(cfg: Config) -> Mesh | None:
    """The ``("views",)`` mesh for ``cfg.train``, or None for a single-view step (B = 1)."""
    batch = cfg.train.batch_size
    if batch == 1:
        return None
    count = resolve_devices(batch, cfg.train.devices)
    return Mesh(np.asarray(jax.devices()[:count]), (AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def by_view(mesh: Mesh) -> NamedSharding:
    """Leading axis (views) split over the mesh."""
    return NamedSharding(mesh, PartitionSpec(AXIS))


def place(tree, sharding: NamedSharding):
    """Every leaf of ``tree`` as a global array with ``sharding``; leaves already so placed are kept.

    Built with ``jax.make_array_from_callback`` from host values, so it works when the mesh
    spans several processes (each process passes the same full values).
    """
    def put(x):
        if isinstance(x, jax.Array) and x.sharding == sharding:
            return x
        if isinstance(x, jax.Array) and x.is_fully_addressable and sharding.is_fully_addressable:
            return jax.device_put(x, sharding)
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def place_step_types(mesh: Mesh, state, batch: dict):
    """The types :func:`place_step_inputs` gives (``jax.ShapeDtypeStruct`` leaves with their shardings), from
    arrays or ``ShapeDtypeStruct`` s: what an ahead-of-time compile of the batched step takes."""
    def typed(tree, sharding):
        return jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=getattr(x, "weak_type", False)),
            tree)

    placed = {k: typed(v, replicated(mesh) if k in SHARED_INPUTS else by_view(mesh)) for k, v in batch.items()}
    return typed(state, replicated(mesh)), placed


def place_step_inputs(mesh: Mesh, state, batch: dict):
    """(state replicated, batch views split over the mesh, what the views share — memory banks, loss weights —
    replicated)."""
    placed = {k: place(v, replicated(mesh) if k in SHARED_INPUTS else by_view(mesh)) for k, v in batch.items()}
    return place(state, replicated(mesh)), placed
