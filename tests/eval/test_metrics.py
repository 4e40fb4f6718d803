"""Metrics: PSNR closed form and skimage agreement, identical images, per-view helper."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from cusgs_jax import losses
from cusgs_jax.eval.metrics import PSNR_MAX_DB, mean_and_per_view, psnr, ssim


@pytest.mark.parametrize("err", [0.5, 0.1, 1e-2, 1e-3])
def test_psnr_constant_error_closed_form(err):
    target = np.random.default_rng(0).uniform(0, 0.5, (12, 10, 3)).astype(np.float32)
    pred = target + np.float32(err)
    assert abs(float(psnr(pred, target)) - (-20 * np.log10(err))) < 1e-3
    # data_range R adds 20 log10(R).
    assert abs(float(psnr(pred * 255, target * 255, 255.0)) - (-20 * np.log10(err))) < 1e-3


def test_psnr_matches_skimage():
    rng = np.random.default_rng(1)
    for i in range(4):
        target = rng.uniform(0, 1, (20 + i, 17, 3))
        pred = np.clip(target + rng.normal(0, 0.02 * (i + 1), target.shape), 0, 1)
        ref = peak_signal_noise_ratio(target, pred, data_range=1.0)
        assert abs(float(psnr(pred.astype(np.float32), target.astype(np.float32))) - ref) < 1e-3
        assert abs(float(jax.jit(psnr)(pred, target)) - ref) < 1e-3


def test_psnr_identical_is_capped():
    x = np.random.default_rng(2).uniform(size=(8, 8, 3)).astype(np.float32)
    assert float(psnr(x, x)) == PSNR_MAX_DB == 100.0
    assert float(psnr(x, x, max_db=60.0)) == 60.0
    assert float(jax.jit(psnr)(np.zeros((4, 4)), np.zeros((4, 4)))) == PSNR_MAX_DB
    with pytest.raises(ValueError):
        psnr(np.zeros((4, 4)), np.zeros((4, 5)))


def test_ssim_is_the_loss_definition():
    assert ssim is losses.ssim
    rng = np.random.default_rng(3)
    a = rng.uniform(size=(24, 20, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                data_range=1.0, channel_axis=-1)
    assert abs(float(ssim(a.astype(np.float32), b.astype(np.float32))) - ref) < 1e-4


def test_mean_and_per_view():
    rng = np.random.default_rng(4)
    targets = rng.uniform(size=(3, 16, 16, 3)).astype(np.float32)
    errs = [0.1, 0.01, 0.0]
    preds = np.stack([t + np.float32(e) for t, e in zip(targets, errs)])
    out = mean_and_per_view(psnr, preds, targets)
    assert set(out) == {"mean", "per_view"}
    np.testing.assert_allclose(out["per_view"], [20.0, 40.0, 100.0], atol=1e-3)
    assert abs(out["mean"] - 160.0 / 3) < 1e-3
    assert all(isinstance(v, float) for v in out["per_view"]) and isinstance(out["mean"], float)
    # Lists work too, with SSIM.
    out_ssim = mean_and_per_view(ssim, list(preds), list(targets))
    assert len(out_ssim["per_view"]) == 3 and abs(out_ssim["per_view"][2] - 1.0) < 1e-6
    with pytest.raises(ValueError):
        mean_and_per_view(psnr, preds[:2], targets)
    with pytest.raises(ValueError):
        mean_and_per_view(psnr, [], [])


def test_psnr_with_a_mask_scores_only_the_valid_pixels():
    rng = np.random.default_rng(7)
    a, b = rng.uniform(size=(2, 20, 30, 3))
    valid = rng.uniform(size=(20, 30)) < 0.7
    expected = peak_signal_noise_ratio(a[valid], b[valid], data_range=1.0)
    assert abs(float(psnr(a, b, mask=valid)) - expected) < 1e-4
    b2 = np.where(valid[..., None], b, 0.0)  # whatever lies outside the mask
    assert float(psnr(a, b2, mask=valid)) == float(psnr(a, b, mask=valid))
    assert float(psnr(a, b, mask=np.ones_like(valid))) == pytest.approx(float(psnr(a, b)), abs=1e-5)
    assert float(psnr(a, b, mask=np.zeros_like(valid))) == PSNR_MAX_DB  # nothing to score
