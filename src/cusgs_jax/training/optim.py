"""Per-group Adam with Scaffold-GS learning rates and log-linear decay (docs/method.md#optimisation)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cusgs_jax.config import OptimConfig


def log_linear_schedule(init: float, final: float, steps: int) -> optax.Schedule:
    """``exp(lerp(log init, log final, t / steps))`` (3DGS ``get_expon_lr_func`` without delay)."""
    if init == final:
        return optax.constant_schedule(init)
    log_init, log_final = jnp.log(init), jnp.log(final)
    return lambda step: _log_lerp(log_init, log_final, step, steps)


def _log_lerp(log_init, log_final, step, steps: int):
    """``exp(lerp(log_init, log_final, clip(step / steps, 0, 1)))``: the schedule's value at ``step``."""
    t = jnp.clip(step / max(steps, 1), 0.0, 1.0)
    return jnp.exp(log_init * (1 - t) + log_final * t)


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


ADAM_BETAS = (0.9, 0.999)  # optax.adam's defaults, as Scaffold-GS's torch.optim.Adam


def batch_scaled(batch_size: int, eps: float, betas=ADAM_BETAS) -> tuple[float, float, tuple[float, float]]:
    """Adam settings for ``batch_size`` views per step: ``(learning-rate factor, eps, (β1, β2))``.

    gsplat's ``simple_trainer.py`` (batch_size · world_size = B views per step) multiplies every
    learning rate by √B, divides eps by √B and uses β = 1 − B(1 − β), so that one step on B views
    moves the parameters about as far as B single-view steps with averaged noise. We follow it
    with one change: β^B instead of its first-order expansion 1 − B(1 − β), which reaches 0 (β1)
    at B = 10 (gsplat marks this as a TODO); the two agree to O((1 − β)²) for small B. B = 1
    returns the single-view settings exactly (bit-identical training).
    """
    if batch_size == 1:
        return 1.0, eps, tuple(betas)
    root = math.sqrt(batch_size)
    return root, eps / root, tuple(b ** batch_size for b in betas)


def group_rates(cfg: OptimConfig, extent: float, batch_size: int = 1) -> dict[str, tuple[float, float]]:
    """{group: (initial, final) learning rate}: ``optim.<group>`` with Scaffold-GS's extent scaling of the
    offsets and :func:`batch_scaled`'s √B for ``batch_size`` views per step."""
    scale = batch_scaled(batch_size, cfg.eps)[0]
    rates = {}
    for name, (init, final) in cfg.groups().items():
        if name == "offsets":
            init, final = init * extent, final * extent
        if batch_size > 1:
            init, final = init * scale, final * scale
        rates[name] = (init, final)
    return rates


def rate_arguments(rates: dict[str, tuple[float, float]]) -> dict[str, jax.Array]:
    """The step's ``learning_rates`` argument for :func:`group_rates` ``rates``: {group: [2] float32}, the
    (log initial, log final) of a decaying group — ``jnp.log`` as :func:`log_linear_schedule` takes them — and
    (rate, rate) of a constant one. As an argument, a sweep over learning rates shares the step's program."""
    def pair(init, final):  # assembled on the host and placed once: eager stacks would each compile a program
        values = (init, final) if init == final else (jnp.log(init), jnp.log(final))
        return np.asarray([np.asarray(v, np.float32) for v in values], np.float32)

    return jax.device_put({name: pair(init, final) for name, (init, final) in rates.items()})


def scale_by_group_rate(group: str, decays: bool, steps: int,
                        default: jax.Array) -> optax.GradientTransformationExtraArgs:
    """``optax.scale_by_learning_rate`` of :func:`log_linear_schedule` (``decays``) or of a constant rate,
    read from the update's ``learning_rates[group]`` (:func:`rate_arguments`; ``default`` when the update is
    given none). The same state and arithmetic as optax's, so the updates are bit for bit those of
    ``optax.adam(log_linear_schedule(...))`` (``tests/training/test_optim.py``)."""

    def init_fn(params):
        del params
        return optax.ScaleByScheduleState(count=jnp.zeros([], jnp.int32))

    def update_fn(updates, state, params=None, *, learning_rates=None, **extra_args):
        del params, extra_args
        rate = default if learning_rates is None else learning_rates[group]
        if decays:
            step_size = -1 * _log_lerp(rate[0], rate[1], state.count, steps)
        else:  # optax.constant_schedule
            step_size = -1 * rate[0]
        updates = jax.tree.map(lambda g: jnp.array(step_size, dtype=g.dtype) * g, updates)
        return updates, optax.ScaleByScheduleState(count=optax.safe_increment(state.count))

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def make_optimizer(cfg: OptimConfig, params, total_steps: int, extent: float,
                   batch_size: int = 1) -> optax.GradientTransformationExtraArgs:
    """Adam (eps from cfg) per group with its own log-linear schedule.

    ``update(grads, state, params, learning_rates=...)`` takes the rates as an argument
    (:func:`rate_arguments`; the train step passes ``batch["learning_rates"]``); without it, those of ``cfg``.

    Args:
      params: the trainable tree (:meth:`cusgs_jax.training.state.TrainState.trainable`); only its
        structure is read, to label every leaf with its group.
      batch_size: views per step B; learning rates, eps and betas follow :func:`batch_scaled`.
    """
    _, eps, (b1, b2) = batch_scaled(batch_size, cfg.eps)
    rates = group_rates(cfg, extent, batch_size)
    defaults = rate_arguments(rates)
    groups = {name: optax.chain(optax.scale_by_adam(b1=b1, b2=b2, eps=eps),
                                scale_by_group_rate(name, init != final, total_steps, defaults[name]))
              for name, (init, final) in rates.items()}
    return optax.multi_transform(groups, param_labels(params))
