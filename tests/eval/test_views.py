"""eval/views.py: the model's size in bytes (model_bytes) against its arrays and parameter counts."""

from __future__ import annotations

import numpy as np

from cusgs_jax.eval.views import count_parameters, model_bytes
from cusgs_jax.model.anchors import AnchorParams, AnchorState


def _anchors(capacity=8, alive=5, n=4, latent=6, table=None):
    rng = np.random.default_rng(0)
    f32 = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    mask = np.arange(capacity) < alive
    return AnchorState(centers=f32(capacity, 3), alive=mask,
                       params=AnchorParams(offsets=f32(capacity, n, 3), log_scaling=f32(capacity, 6),
                                           latent=f32(capacity, latent),
                                           query_table=None if table is None else f32(capacity, n, table)))


def test_model_bytes_is_the_sum_of_the_alive_rows_nets_and_banks():
    anchors = _anchors(table=2)
    nets = {"decoder": {"w0": np.zeros((9, 16), np.float32), "b0": np.zeros(16, np.float32)},
            "appearance": np.zeros((7, 4), np.float32)}
    banks = {"semantic": np.zeros((32, 10), np.float32)}
    per_alive_row = 4 * (3 + 4 * 3 + 6 + 6 + 4 * 2)  # centres, offsets, scaling, latent, query table (float32)
    want = 5 * per_alive_row + 4 * (9 * 16 + 16) + 4 * 7 * 4 + 4 * 32 * 10
    assert model_bytes(anchors, nets, banks) == want
    assert model_bytes(anchors, nets, banks) == 4 * count_parameters(anchors, nets, banks)["total"]
    assert model_bytes(anchors, nets) == want - 4 * 32 * 10  # banks count
    assert model_bytes(_anchors(alive=3), {}) == 3 * 4 * (3 + 12 + 6 + 6)  # dead slots do not


def test_model_bytes_counts_each_arrays_own_dtype():
    anchors = _anchors(alive=2, table=None)
    nets = {"decoder": {"w0": np.zeros((3, 5), np.float16)}}
    assert model_bytes(anchors, nets) == 2 * 4 * (3 + 12 + 6 + 6) + 2 * 15
