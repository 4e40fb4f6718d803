"""Active-Gaussian compaction: only the Gaussians that pass Scaffold's opacity mask reach the splatter.

Scaffold-GS decodes N Gaussians for every visible anchor and switches off those whose
opacity head is ≤ 0 (``decode_gaussians``'s ``active``); on real scenes four in five
decoded Gaussians are switched off. Projection, the depth sort, tile binning,
compositing and their backward would pay for them all. Here the active ones are
gathered into a static capacity ``G_act`` first, and everything the splatter returns
per Gaussian is mapped back to decoded order for the densification statistics.

Naming (:mod:`cusgs_jax.types`): G = S·N decoded Gaussians, Ga = G_act active capacity.

Both directions are gathers, never scatters (XLA's CPU scatter runs element by element):
the gather ``x[index]`` differentiates to a gather of the cotangent at ``position``
(:func:`gather_active`'s custom VJP), since the map decoded → active is injective.
Masked Gaussians contributed exactly zero to the render (opacity 0 is culled by the
projection), so the loss and every gradient equal the uncompacted ones.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cusgs_jax.model.decode import Gaussians
from cusgs_jax.scan import first_true, running_sum
from cusgs_jax.splat import RenderOutput


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ActiveSet:
    """Where each active Gaussian sits in the compacted arrays.

    Attributes:
      index: [Ga] int32 decoded index of compacted entry k (padding entries hold 0).
      valid: [Ga] bool, entry k holds an active Gaussian.
      position: [G] int32 compacted index of decoded Gaussian g (meaningful where ``kept``).
      kept: [G] bool, Gaussian g is active and fitted in the capacity.
      count: [] int32 active Gaussians of the view.
      overflow: [] int32 active Gaussians that did not fit in Ga (0 = exact).
    """

    index: jax.Array
    valid: jax.Array
    position: jax.Array
    kept: jax.Array
    count: jax.Array
    overflow: jax.Array


def select_active(active: jax.Array, capacity: int) -> ActiveSet:
    """The first ``capacity`` active Gaussians in decoded order.

    Args:
      active: [G] bool.
      capacity: static Ga ≥ 1.
    """
    num = active.shape[0]
    rank = running_sum(active) - 1  # [G] index among the active ones
    count = rank[-1] + 1 if num else jnp.int32(0)
    kept = active & (rank < capacity)
    index = first_true(active, capacity)
    valid = jnp.arange(capacity) < count
    return ActiveSet(index=index, valid=valid, position=jnp.clip(rank, 0, capacity - 1).astype(jnp.int32),
                     kept=kept, count=count.astype(jnp.int32),
                     overflow=jnp.maximum(count - capacity, 0).astype(jnp.int32))


def _bcast(mask, x):
    return mask.reshape(mask.shape + (1,) * (x.ndim - 1))


@jax.custom_vjp
def gather_active(x: jax.Array, chosen: ActiveSet) -> jax.Array:
    """[G, ...] → [Ga, ...]: the active rows, zero in padding entries (differentiable in ``x``)."""
    return jnp.where(_bcast(chosen.valid, x), x[chosen.index], jnp.zeros((), x.dtype))


def _gather_fwd(x, chosen):
    return gather_active(x, chosen), chosen


def _gather_bwd(chosen, cotangent):
    # the transpose of an injective gather is a gather of the cotangent at the inverse map
    grad = jnp.where(_bcast(chosen.kept, cotangent[:1]), cotangent[chosen.position], 0).astype(cotangent.dtype)
    return grad, None


gather_active.defvjp(_gather_fwd, _gather_bwd)


def scatter_back(y: jax.Array, chosen: ActiveSet, fill=0) -> jax.Array:
    """[Ga, ...] → [G, ...] in decoded order (``fill`` for masked Gaussians); a gather, not differentiated."""
    return jnp.where(_bcast(chosen.kept, y[:1]), y[chosen.position], jnp.asarray(fill, y.dtype))


def compact_gaussians(gaussians: Gaussians, chosen: ActiveSet) -> Gaussians:
    """The active Gaussians [Ga]; padding entries have opacity 0 (culled by the projection)."""
    return Gaussians(
        means=gather_active(gaussians.means, chosen),
        quats=gather_active(gaussians.quats, chosen),  # zero in padding: the projection reads it as the identity
        scales=gather_active(gaussians.scales, chosen),
        opacities=gather_active(gaussians.opacities, chosen),
        colors=gather_active(gaussians.colors, chosen),
        active=chosen.valid,
        anchor_index=jnp.where(chosen.valid, gaussians.anchor_index[chosen.index], 0),
    )


def expand_render(out: RenderOutput, chosen: ActiveSet) -> RenderOutput:
    """A render of the compacted Gaussians with its per-Gaussian fields back in decoded order [G]."""
    return out._replace(means2d=scatter_back(jax.lax.stop_gradient(out.means2d), chosen),
                        radii=scatter_back(out.radii, chosen), visible=scatter_back(out.visible, chosen, False),
                        significance=scatter_back(out.significance, chosen), hits=scatter_back(out.hits, chosen))
