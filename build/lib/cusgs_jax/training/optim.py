"""Per-group Adam with Scaffold-GS learning rates and log-linear decay (DESIGN.md §1)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from cusgs_jax.config import OptimConfig


def log_linear_schedule(init: float, final: float, steps: int) -> optax.Schedule:
    """``exp(lerp(log init, log final, t / steps))`` (3DGS ``get_expon_lr_func`` without delay)."""
    if init == final:
        return optax.constant_schedule(init)
    log_init, log_final = jnp.log(init), jnp.log(final)

    def schedule(step):
        t = jnp.clip(step / max(steps, 1), 0.0, 1.0)
        return jnp.exp(log_init * (1 - t) + log_final * t)

    return schedule


GROUP_OF_PATH = {
    ("anchor", "offsets"): "offsets",
    ("anchor", "latent"): "latent",
    ("anchor", "log_scaling"): "scaling",
    ("anchor", "query_table"): "features",
    ("decoder", "opacity"): "mlp_opacity",
    ("decoder", "cov"): "mlp_cov",
    ("decoder", "color"): "mlp_color",
    ("appearance",): "appearance",
    ("queries",): "features",
    ("memory",): "features",
}


def _key_name(entry) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def param_labels(params) -> object:
    """Group label of every leaf of the parameter tree (see ``GROUP_OF_PATH``)."""

    def label(path, _):
        names = tuple(_key_name(p) for p in path)
        for prefix, group in GROUP_OF_PATH.items():
            if names[: len(prefix)] == prefix:
                return group
        raise KeyError(f"no optimiser group for parameter {'/'.join(names)}")

    return jax.tree_util.tree_map_with_path(label, params)


def make_optimizer(cfg: OptimConfig, params, total_steps: int, extent: float) -> optax.GradientTransformation:
    """Adam (eps from cfg) per group with its own log-linear schedule.

    Args:
      params: the trainable tree (:meth:`cusgs_jax.training.state.TrainState.trainable`); only its
        structure is read, to label every leaf with its group.
    """
    groups = {}
    for name, (init, final) in cfg.groups().items():
        if name == "offsets":
            init, final = init * extent, final * extent
        groups[name] = optax.adam(log_linear_schedule(init, final, total_steps), eps=cfg.eps)
    return optax.multi_transform(groups, param_labels(params))
