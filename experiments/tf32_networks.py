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


def apply_mlp_tf32(params: dict, x: jax.Array, precision=None) -> jax.Array:
    """:func:`cusgs_jax.nn.apply_mlp` with every matmul's operands in TF32 (``precision`` ignored)."""
    layers = len(params) // 2
    for i in range(layers):
        x = jnp.matmul(to_tf32(x), to_tf32(params[f"w{i}"]), precision=HIGHEST) + params[f"b{i}"]
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
