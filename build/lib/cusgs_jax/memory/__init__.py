"""Per-model feature memory.

:mod:`.psc` builds each model's bank of Principal Scene Components (M3's greedy
cosine-threshold reduction, exact and chunked); :mod:`.attention` retrieves a
feature per pixel from a bank by memory attention (pure JAX).
"""

from cusgs_jax.memory.attention import (
    apply_adapter,
    attend,
    attention_weights,
    init_memory_head,
    masked_softmax,
    precompute_keys,
    safe_normalize,
)
from cusgs_jax.memory.psc import M3_GAMMAS, PSCBank, build, build_per_model

__all__ = [
    "M3_GAMMAS", "PSCBank", "apply_adapter", "attend", "attention_weights", "build", "build_per_model",
    "init_memory_head", "masked_softmax", "precompute_keys", "safe_normalize",
]
