"""What TF32 in the networks would cost: the README's main job with the heads' matmuls emulated in TF32 on a CPU.

``model.matmul_precision=default`` lets an NVIDIA GPU (Ampere and later) compute the decoder's and
the query heads' float32 matmuls in TF32: each operand rounded to 10 explicit mantissa bits (round to
nearest, ties away from zero, as ``cvt.rna.tf32.f32``), products summed in float32. A CPU has no
TF32, so this script emulates it exactly that way — operands rounded, then a float32 matmul at
HIGHEST — in ``cusgs_jax.nn.apply_mlp`` (every network matmul goes through it), and runs
``cusgs-train`` with the given overrides. Geometry stays at full float32, as in the library.
The accumulation order of a tensor core differs from the CPU's; that is float32 rounding, far
below TF32's.

    python experiments/tf32_networks.py hydra.run.dir=outputs/tf32 train.progress=false
    (compare eval.json's psnr with the same command's run of plain cusgs-train)
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp

from cusgs_jax import nn
from cusgs_jax.model import decode, queries
from cusgs_jax.precision import HIGHEST


def to_tf32(x: jax.Array) -> jax.Array:
    """float32 → the nearest TF32 value (10 explicit mantissa bits; ties away from zero), as float32."""
    bits = jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.uint32)
    rounded = (bits + jnp.uint32(0x1000)) & jnp.uint32(0xFFFFE000)
    return jax.lax.bitcast_convert_type(rounded, jnp.float32)


@jax.custom_vjp
def matmul_tf32(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b`` as a TF32 GEMM computes it: both operands rounded to TF32, products summed in float32. The
    backward pass's two GEMMs (``g @ bᵀ``, ``aᵀ @ g``) round their operands the same way, as on the GPU (a
    bit cast has no derivative, so the rounding needs this custom VJP)."""
    return jnp.matmul(to_tf32(a), to_tf32(b), precision=HIGHEST)


def _matmul_tf32_fwd(a, b):
    return matmul_tf32(a, b), (a, b)


def _matmul_tf32_bwd(res, g):
    a, b = res
    ga = jnp.matmul(to_tf32(g), to_tf32(jnp.swapaxes(b, -1, -2)), precision=HIGHEST)
    a2 = a.reshape(-1, a.shape[-1])
    gb = jnp.matmul(to_tf32(a2.T), to_tf32(g.reshape(-1, g.shape[-1])), precision=HIGHEST)
    return ga, gb


matmul_tf32.defvjp(_matmul_tf32_fwd, _matmul_tf32_bwd)


def apply_mlp_tf32(params: dict, x: jax.Array, precision=None) -> jax.Array:
    """:func:`cusgs_jax.nn.apply_mlp` with every matmul a TF32 GEMM (:func:`matmul_tf32`; ``precision`` ignored)."""
    layers = len(params) // 2
    for i in range(layers):
        x = matmul_tf32(x, params[f"w{i}"]) + params[f"b{i}"]
        if i < layers - 1:
            x = jax.nn.relu(x)
    return x


def main() -> None:
    for module in (nn, decode, queries):
        module.apply_mlp = apply_mlp_tf32
    from cusgs_jax.app.train import main as train_main

    sys.argv[0] = "cusgs-train"
    train_main(sys.argv[1:])


if __name__ == "__main__":
    main()
