"""Matmul precision: geometry at full float32 on every backend (docs/scaling.md#on-a-gpu).

On NVIDIA GPUs since Ampere, XLA computes a float32 ``dot_general`` whose precision is left at
DEFAULT in TF32 (inputs rounded to 10 mantissa bits; JAX docs "Precision", jax-ml/jax#12008). A
relative error of 1e-4 in camera coordinates is a tenth of a pixel at a 1000 px focal length, so every
contraction of geometry — projection, covariances, lenses, SH evaluation, compositing weights,
baking — passes :data:`HIGHEST` explicitly. The CPU ignores the setting, so the CPU tests guard it by
reading the traced programs (:func:`cusgs_jax.testing.jaxpr_checks.dot_precisions`), not by numbers.

The networks (the anchor decoder's heads and the query heads) take ``model.matmul_precision``
(:data:`NETWORK_PRECISIONS`): ``highest`` (the default: the same numbers on every backend) or
``default`` (the backend's choice: TF32 on such GPUs).
"""

from __future__ import annotations

import jax

HIGHEST = jax.lax.Precision.HIGHEST

#: ``model.matmul_precision`` spellings → :class:`jax.lax.Precision`.
NETWORK_PRECISIONS = {"highest": jax.lax.Precision.HIGHEST, "default": jax.lax.Precision.DEFAULT}


def network_precision(name: str) -> jax.lax.Precision:
    """The :class:`jax.lax.Precision` of a ``model.matmul_precision`` value (``highest`` or ``default``)."""
    return NETWORK_PRECISIONS[name]
