"""eval/views.py: the model's size in bytes (model_bytes) against its arrays and parameter counts; masked
evaluation."""

from __future__ import annotations

import numpy as np

import types

from cusgs_jax.eval.views import count_parameters, evaluate_views, model_bytes
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


def test_a_scene_with_a_valid_pixel_mask_is_scored_on_its_valid_pixels_only():
    """data.undistort=mask: a render that is right inside the mask and wrong outside scores PSNR 100 and SSIM 1;
    LPIPS sees both images with the invalid pixels zeroed."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (2, 16, 20, 3), dtype=np.uint8)
    valid = np.ones((2, 16, 20), bool)
    valid[:, :3] = False
    valid[1, :, -4:] = False
    scene = types.SimpleNamespace(images=images, valid=valid, names=("a.png", "b.png"), width=20, height=16,
                                  Ks=np.tile(np.eye(3, dtype=np.float32), (2, 1, 1)),
                                  viewmats=np.tile(np.eye(4, dtype=np.float32), (2, 1, 1)),
                                  camera_centers=np.zeros((2, 3)), train_indices=np.array([0]))

    def render(anchors, nets, camera, app):
        view = render.calls
        render.calls += 1
        target = images[view].astype(np.float32) / 255.0
        return (np.where(valid[view][..., None], target, 1.0 - target),)

    seen = []

    def lpips(a, b):
        seen.append((np.asarray(a[0]), np.asarray(b[0])))
        return np.array([float(np.abs(a - b).max())])

    render.calls = 0
    result = evaluate_views(render, None, {}, scene, [0, 1], lpips={"lpips_probe": lpips})
    assert result["psnr"] == 100.0 and abs(result["ssim"] - 1.0) < 1e-5 and result["lpips_probe"] == 0.0
    for (a, b), mask in zip(seen, valid):
        assert np.all(a[~mask] == 0) and np.all(b[~mask] == 0)
    render.calls = 0
    unmasked = evaluate_views(render, None, {}, types.SimpleNamespace(**{**vars(scene), "valid": None}), [0, 1])
    assert unmasked["psnr"] < 20 and unmasked["ssim"] < 0.99
