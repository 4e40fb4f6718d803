"""Training losses: L1, SSIM (D-SSIM), Scaffold-GS volume regulariser, and their sum.

Every function here is a pure, jittable and differentiable JAX function (no Flax,
no host callbacks). Shapes are static, so Python-level checks run at trace time.

SSIM follows ``skimage.metrics.structural_similarity(pred, target,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
channel_axis=-1)`` exactly:

* the window is scipy's sampled Gaussian, ``radius = int(truncate * sigma + 0.5)``
  with ``truncate = 3.5`` (11 taps for sigma = 1.5), normalised to sum 1,
  applied separably (rows then columns), each channel independently;
* skimage filters with ``mode='reflect'`` and then discards a border of
  ``pad = (win_size - 1) // 2`` pixels before averaging. Every kept pixel's window
  lies entirely inside the image, so the reflected samples never reach the mean.
  We therefore filter in "valid" mode (no padding at all), which yields exactly
  the cropped map, ``[H - 2 * pad, W - 2 * pad, C]``, at lower cost;
* population (co)variances (computed from data shifted by R/2 for float32
  accuracy; the shift cancels exactly in exact arithmetic), ``C1 = (0.01 * R)**2``, ``C2 = (0.03 * R)**2``;
* mean over the cropped map of each channel, then mean over channels (the
  same thing as one mean over ``[H', W', C]``, since channels share the map size).

The filter is a sum of shifted slices (pure element-wise arithmetic) rather than a
convolution primitive, so it is exact float32 on every backend (GPU convolutions
may silently run in TF32) and it fuses well for the small 11-tap window.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "gaussian_window",
    "image_loss",
    "l1",
    "masked_mean",
    "ssim",
    "ssim_loss",
    "ssim_map",
    "volume_regularizer",
    "zero_invalid",
]

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # skimage's choice: an 11-tap window for sigma = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def gaussian_window(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE) -> np.ndarray:
    """scipy.ndimage's 1D Gaussian kernel: [2r+1] float64, r = int(truncate*sigma + 0.5), sums to 1."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    phi = np.exp(-0.5 / (sigma * sigma) * x * x)
    return phi / phi.sum()


def _float_pair(pred, target):
    """Both images as arrays of one common floating dtype."""
    pred = jnp.asarray(pred)
    target = jnp.asarray(target)
    dtype = jnp.promote_types(pred.dtype, target.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.promote_types(dtype, jnp.float32)
    return pred.astype(dtype), target.astype(dtype)


def _filter_valid(x: jnp.ndarray, window: np.ndarray) -> jnp.ndarray:
    """Separable 'valid' correlation of x [H, W, N] with window [K] → [H-K+1, W-K+1, N]."""
    return _correlate_valid(x, tuple(float(v) for v in window))


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _correlate_valid(x: jnp.ndarray, window: tuple) -> jnp.ndarray:
    k = len(window)
    w = [jnp.asarray(v, dtype=x.dtype) for v in window]
    h_out = x.shape[0] - k + 1
    y = w[0] * x[0:h_out]
    for i in range(1, k):
        y = y + w[i] * x[i:i + h_out]
    w_out = x.shape[1] - k + 1
    z = w[0] * y[:, 0:w_out]
    for i in range(1, k):
        z = z + w[i] * y[:, i:i + w_out]
    return z


def _correlate_valid_fwd(x, window):
    return _correlate_valid(x, window), None


def _correlate_valid_bwd(window, _, cotangent):
    # The filter is linear; its transpose is the 'full' convolution, i.e. the valid correlation of the
    # cotangent padded by K−1 on both sides of H and W with the flipped window. One fused pass instead of
    # the K pads per axis that transposing every slice would materialise (~0.4 s per step at 640×480).
    k = len(window)
    padded = jnp.pad(cotangent, ((k - 1, k - 1), (k - 1, k - 1), (0, 0)))
    return (_correlate_valid(padded, window[::-1]),)


_correlate_valid.defvjp(_correlate_valid_fwd, _correlate_valid_bwd)


@functools.partial(jax.jit, static_argnames=("sigma",))
def ssim_map(pred, target, *, data_range: float = 1.0, sigma: float = SSIM_SIGMA) -> jnp.ndarray:
    """Per-pixel SSIM on the border-cropped grid.

    Args:
      pred, target: [H, W, C] (or [H, W], treated as C = 1) images in [0, data_range].
        H and W must be at least the window size (11 for sigma = 1.5).
      data_range: R in C1 = (0.01 R)², C2 = (0.03 R)².
      sigma: Gaussian window σ (window radius int(3.5 σ + 0.5), as skimage); static.
    Returns:
      [H - 2r, W - 2r, C] SSIM values; equals skimage's ``full=True`` map cropped by
      r = (win_size - 1) // 2 on every side.
    """
    pred, target = _float_pair(pred, target)
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {pred.shape} vs {target.shape}")
    if pred.ndim == 2:
        pred, target = pred[..., None], target[..., None]
    if pred.ndim != 3:
        raise ValueError(f"expected [H, W, C] or [H, W] images, got shape {pred.shape}")
    window = gaussian_window(sigma)
    k = window.shape[0]
    if pred.shape[0] < k or pred.shape[1] < k:
        raise ValueError(f"image {pred.shape[:2]} is smaller than the {k}x{k} SSIM window")

    # (Co)variances are shift-invariant; moments of data centred on R/2 (|x| ≤ R/2 instead
    # of ≤ R) lose ~4-8x less to the cancellation in E[x²] − E[x]² in float32. The window
    # sums to 1, so adding the shift back to the filtered means is exact up to rounding.
    shift = 0.5 * data_range
    x, y = pred - shift, target - shift
    c = pred.shape[-1]
    stacked = jnp.concatenate([x, y, x * x, y * y, x * y], axis=-1)
    filtered = _filter_valid(stacked, window)
    mx, my, uxx, uyy, uxy = (filtered[..., i * c:(i + 1) * c] for i in range(5))
    vx = uxx - mx * mx
    vy = uyy - my * my
    vxy = uxy - mx * my
    ux, uy = mx + shift, my + shift

    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    a1 = 2 * ux * uy + c1
    a2 = 2 * vxy + c2
    b1 = ux * ux + uy * uy + c1  # ≥ C1 > 0
    b2 = vx + vy + c2  # ≥ C2 up to rounding of vx, vy ≥ 0 (≪ C2 for data in [0, R])
    return (a1 * a2) / (b1 * b2)


def ssim(pred, target, *, data_range: float = 1.0, sigma: float = SSIM_SIGMA, mask=None) -> jnp.ndarray:
    """Mean SSIM of two [H, W, C] (or [H, W]) images in [0, data_range] → scalar.

    Matches skimage's Gaussian-weighted, population-covariance SSIM (see module
    docstring) to float rounding. Identical images give 1 (up to rounding), and the
    gradient is finite everywhere, including constant and all-zero images.

    ``mask``: optional [H, W] valid-pixel mask (bool, or 0/1). Both images are first set to 0
    outside it (:func:`zero_invalid`), so a window that straddles the mask's edge sees the same
    constant in both, and the mean runs over the map's valid pixels (1 when none is left after the
    border crop). Neither the value nor the gradient depends on the pixels outside the mask.
    """
    if mask is None:
        return jnp.mean(ssim_map(pred, target, data_range=data_range, sigma=sigma))
    pred, target = zero_invalid(pred, target, mask)
    values = ssim_map(pred, target, data_range=data_range, sigma=sigma)
    r = (gaussian_window(sigma).shape[0] - 1) // 2
    cropped = jnp.asarray(mask, values.dtype)[r:pred.shape[0] - r, r:pred.shape[1] - r]  # the map's grid
    return jnp.where(jnp.any(cropped > 0), masked_mean(values, cropped), 1.0)


def zero_invalid(pred, target, mask) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``pred`` and ``target`` [H, W, C] with the pixels outside the valid-pixel ``mask`` [H, W] set to 0
    in both.

    What the masked loss and metrics compare (the invalid pixels of an image undistorted with
    ``data.undistort=mask`` hold no content): those pixels add no error and no gradient, and since
    they are the same constant in both images, what the target holds there cannot change a windowed
    statistic (SSIM, LPIPS) at the valid pixels next to them.
    """
    pred, target = _float_pair(pred, target)
    keep = _broadcast_mask(jnp.asarray(mask).astype(bool), pred)
    zero = jnp.zeros((), pred.dtype)
    return jnp.where(keep, pred, zero), jnp.where(keep, target, zero)


def ssim_loss(pred, target, *, data_range: float = 1.0, sigma: float = SSIM_SIGMA) -> jnp.ndarray:
    """D-SSIM term: 1 − ssim(pred, target), scalar. pred, target: [H, W, C]."""
    return 1.0 - ssim(pred, target, data_range=data_range, sigma=sigma)


def l1(pred, target, mask=None) -> jnp.ndarray:
    """Mean absolute error → scalar.

    Args:
      pred, target: [H, W, C] images (any equal shapes work).
      mask: optional per-pixel weights, [H, W] (broadcast over C) or broadcastable
        to pred's shape; bool or float. With a mask the result is the weighted mean
        Σ m·|pred − target| / Σ m (over all broadcast elements), and 0 if Σ m = 0
        (:func:`masked_mean`).
    """
    pred, target = _float_pair(pred, target)
    return masked_mean(jnp.abs(pred - target), mask)


def masked_mean(values, mask=None) -> jnp.ndarray:
    """Σ m·values / Σ m over all elements → scalar; the plain mean without a mask.

    Args:
      values: [H, W, C] (any shape) floating array.
      mask: optional weights, [H, W] (broadcast over the last axis) or broadcastable to
        ``values``; bool or float (e.g. a valid-pixel mask, ``SceneData.valid``). The result is 0
        when Σ m = 0. What :func:`l1`, the masked PSNR (:func:`cusgs_jax.eval.metrics.psnr`) and
        the training step's MSE average with.
    """
    values = jnp.asarray(values)
    if mask is None:
        return jnp.mean(values)
    weights = _broadcast_mask(mask, values).astype(values.dtype)
    total = jnp.sum(weights)
    return jnp.sum(weights * values) / jnp.where(total > 0, total, 1.0)


def _broadcast_mask(mask, like: jnp.ndarray) -> jnp.ndarray:
    """A per-pixel ``mask`` ([H, W] for an [H, W, C] ``like``, or broadcastable) broadcast to ``like``'s shape."""
    mask = jnp.asarray(mask)
    if mask.ndim == like.ndim - 1:
        mask = mask[..., None]
    return jnp.broadcast_to(mask, like.shape)


def volume_regularizer(scales, mask=None) -> jnp.ndarray:
    """Scaffold-GS ``scaling_reg``: mean over Gaussians of the scale product → scalar.

    Args:
      scales: [G, 3] (positive, post-activation) Gaussian scales.
      mask: optional [G] bool; the mean then runs over the selected Gaussians only
        (0 when none is selected). Unselected rows may hold anything, inf/nan
        included: they affect neither the value nor the gradient.
    """
    scales = jnp.asarray(scales)
    if not jnp.issubdtype(scales.dtype, jnp.floating):
        scales = scales.astype(jnp.float32)
    if mask is None:
        return jnp.mean(jnp.prod(scales, axis=-1))
    mask = jnp.asarray(mask).astype(bool)
    safe = jnp.where(mask[..., None], scales, jnp.ones_like(scales))
    vol = jnp.where(mask, jnp.prod(safe, axis=-1), jnp.zeros((), scales.dtype))
    count = jnp.sum(mask).astype(scales.dtype)
    return jnp.sum(vol) / jnp.maximum(count, 1.0)


def image_loss(pred, target, scales=None, mask=None, *, pixel_mask=None, l1_weight: float = 0.8,
               ssim_weight: float = 0.2, volume_weight: float = 0.01):
    """Total training loss l1_weight·L1 + ssim_weight·(1 − SSIM) + volume_weight·volume.

    Args:
      pred, target: [H, W, C] images in [0, 1].
      scales: optional [G, 3] Gaussian scales for the volume regulariser; without it
        the volume term is 0.
      mask: optional [G] bool selecting the Gaussians the regulariser averages over
        (Scaffold-GS: the neural Gaussians visible / kept in this view).
      pixel_mask: optional [H, W] valid-pixel mask (bool or 0/1, e.g. ``SceneData.valid``): L1 is
        the mean over the valid pixels and SSIM the masked mean of :func:`ssim`; pixels outside it
        add neither loss nor gradient.
      l1_weight, ssim_weight, volume_weight: term weights (may be traced values).
    Returns:
      (loss, terms): scalar loss and a dict of scalars
      {"l1", "ssim", "ssim_loss", "volume", "loss"} — "ssim" is the similarity itself,
      "ssim_loss" = 1 − ssim, "volume" the unweighted regulariser.
    """
    l1_term = l1(pred, target, pixel_mask)
    ssim_term = ssim(pred, target, mask=pixel_mask)
    d_ssim = 1.0 - ssim_term
    if scales is None:
        volume = jnp.zeros((), l1_term.dtype)
    else:
        volume = volume_regularizer(scales, mask).astype(l1_term.dtype)
    loss = l1_weight * l1_term + ssim_weight * d_ssim + volume_weight * volume
    terms = {"l1": l1_term, "ssim": ssim_term, "ssim_loss": d_ssim, "volume": volume, "loss": loss}
    return loss, terms
