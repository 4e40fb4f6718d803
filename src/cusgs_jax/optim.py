"""Per-group Adam with Scaffold-GS learning rates and log-linear decay (DESIGN.md §1)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """(initial, final) learning rate per parameter group; decay is log-linear over the run.

    ``offsets`` is multiplied by the scene extent (Scaffold-GS ``spatial_lr_scale``).
    """

    offsets: tuple[float, float] = (0.01, 0.0001)
    latent: tuple[float, float] = (0.0075, 0.0075)
    scaling: tuple[float, float] = (0.007, 0.007)
    mlp_opacity: tuple[float, float] = (0.002, 0.00002)
    mlp_cov: tuple[float, float] = (0.004, 0.004)
    mlp_color: tuple[float, float] = (0.008, 0.00005)
    appearance: tuple[float, float] = (0.05, 0.0005)
    features: tuple[float, float] = (0.0005, 0.0005)  # query heads and memory heads (M3 f_emb)
    eps: float = 1e-15


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
    """Adam (eps from cfg) per group with its own log-linear schedule."""
    groups = {}
    for field in dataclasses.fields(cfg):
        if field.name == "eps":
            continue
        init, final = getattr(cfg, field.name)
        if field.name == "offsets":
            init, final = init * extent, final * extent
        groups[field.name] = optax.adam(log_linear_schedule(init, final, total_steps), eps=cfg.eps)
    return optax.multi_transform(groups, param_labels(params))


def reset_rows(opt_state, rows, capacity: int, group: str = "anchor"):
    """Zero the optimiser moments of anchor slots ``rows`` (new anchors start fresh).

    Args:
      rows: [A] bool mask of slots to reset.
      group: reset the capacity-shaped moments whose tree path names this key
        (``"anchor"``: the anchor parameters; ``"table"``: the per-Gaussian query table).
    """
    def reset(path, x):
        names = {_key_name(p) for p in path}
        if group in names and isinstance(x, jax.Array) and x.ndim >= 1 and x.shape[0] == capacity:
            mask = rows.reshape((capacity,) + (1,) * (x.ndim - 1))
            return jnp.where(mask, jnp.zeros_like(x), x)
        return x

    return jax.tree_util.tree_map_with_path(reset, opt_state)
