"""Optional foundation-model extractors: CLIP (open_clip) and DINOv2 (timm) patch tokens.

=======  ===========  ==========================================================================
model    D            what
=======  ===========  ==========================================================================
clip     embed dim    open_clip ViT patch tokens (after ``ln_post``), projected into the joint
                      embedding space (ViT-B-16: 512)
dinov2   model width  DINOv2 last-layer patch tokens (after the final norm) via timm
                      (vit_small_patch14_dinov2: 384)
=======  ===========  ==========================================================================

Both need LOCAL weights (``weights=PATH``; nothing is ever downloaded) and the ``pretrained`` extra
(``pip install -e '.[pretrained]'``: torch, open_clip_torch, timm). Those packages are imported only
when an extractor is built, never when this module is imported (:mod:`cusgs_jax.extract.scene`
imports it at module level).

Weights:

* clip: an open_clip checkpoint file of ``arch`` (default ViT-B-16), e.g.
  ``open_clip_pytorch_model.bin`` of laion/CLIP-ViT-B-16-laion2B-s34B-b88K, or the folder holding
  it. Loaded by ``open_clip.create_model(arch, pretrained=FILE)``.
* dinov2: a timm checkpoint of ``arch`` (default vit_small_patch14_dinov2): ``model.safetensors``
  of timm/vit_small_patch14_dinov2.lvd142m (or its folder), or the original
  ``dinov2_vits14_pretrain.pth`` (timm converts it). Loaded by ``timm.create_model(arch,
  pretrained=True, pretrained_cfg_overlay={"file": FILE}, dynamic_img_size=True)``. A Hugging Face
  *transformers* snapshot (facebook/dinov2-small) has other parameter names and is refused with a
  message saying what to use instead.

``net=`` (Python only, not on the command line) hands over an already built torch module instead
of ``weights`` — an open_clip CLIP model (or its ``.visual``), or a timm DINOv2 ViT built with
``dynamic_img_size=True``; everything after loading (resizing, normalisation, token layout,
output format) is the same code. The tests use it with randomly initialised real architectures.

Preprocessing and output:

* clip: the whole image is resized to the model's square input (``visual.image_size``, 224),
  normalised with ``visual.preprocess_cfg``'s mean/std (OpenAI's by default); the g×g token grid
  (14×14) is area-resized to the image aspect — long side g, denser for tiny images whose rounding
  would change the aspect (:func:`~cusgs_jax.extract.base.fit_aspect`) — or to ``resolution``.
* dinov2: the image keeps its aspect, its long side resized to ``input_size`` (448) and both sides
  rounded to multiples of the patch (14), ImageNet-normalised; the map is the gh×gw patch grid
  (32×24 for a 4:3 image) or area-resized to ``resolution``.

torchvision: open_clip and timm import it. PyPI's torchvision wheels are CUDA builds whose C++
ops (``torchvision/_C.so``) cannot load beside a CPU-only torch, and torchvision 0.28 then fails
at import (``operator torchvision::nms does not exist``) because it registers fake kernels for
``nms``/``qnms`` unconditionally. When the ops library does not load, we declare those two
operator schemas (no kernels) before importing open_clip/timm (:func:`_prepare_torchvision`), so
the import works; detection ops stay unavailable, and neither extractor uses them.

The extractors follow the protocol of :mod:`cusgs_jax.extract.scene`: ``cls(model, options)``
with ``.opts`` and ``.source``, called as ``extractor(view, size) -> [h, w, D]``.
"""

from __future__ import annotations

import importlib.util
import logging
import pathlib
import sys
from collections.abc import Sequence

import numpy as np

from cusgs_jax.data.features import FeatureError
from cusgs_jax.data.resize import resize_features
from cusgs_jax.extract.base import BUILT_IN_EXTRACTORS, View, fit_aspect, pop_options, resized_image

log = logging.getLogger("cusgs_jax")

_EXTRA = "pip install -e '.[pretrained]' (torch, open_clip_torch, timm)"
_INSTALL_HINT = {"clip": _EXTRA, "dinov2": _EXTRA}
_WEIGHTS_HINT = {
    "clip": ("an open_clip checkpoint file of the --arch model (e.g. open_clip_pytorch_model.bin of "
             "laion/CLIP-ViT-B-16-laion2B-s34B-b88K, with --arch ViT-B-16) or the folder holding it, "
             "copied to this machine"),
    "dinov2": ("a timm DINOv2 checkpoint of the --arch model (model.safetensors of "
               "timm/vit_small_patch14_dinov2.lvd142m, or the original dinov2_vits14_pretrain.pth, "
               "with --arch vit_small_patch14_dinov2) or the folder holding it, copied to this machine"),
}
# Checkpoint names looked for inside a weights folder, in order.
_CHECKPOINTS = {
    "clip": ("open_clip_model.safetensors", "open_clip_pytorch_model.bin", "model.safetensors",
             "pytorch_model.bin"),
    "dinov2": ("model.safetensors", "pytorch_model.bin"),
}
OPENAI_MEAN, OPENAI_STD = (0.48145466, 0.4578275, 0.40821073), (0.26862954, 0.26130258, 0.27577711)
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)

_torchvision_stubs = None  # the torch.library.Library holding the stub schemas (kept alive)


def _require_weights(model: str, weights) -> pathlib.Path:
    """The existing local checkpoint file for ``model`` (a folder: the checkpoint inside), or a
    FeatureError saying what to pass."""
    if not weights:
        raise FeatureError(
            f"model {model!r} needs local weights: pass --weights PATH (weights=PATH), {model} "
            f"weights being {_WEIGHTS_HINT[model]}. Nothing is ever downloaded. Install the "
            f"optional dependencies with `{_INSTALL_HINT[model]}`.")
    path = pathlib.Path(weights).expanduser()
    if not path.exists():
        raise FeatureError(f"weights for model {model!r} not found: {path} does not exist; pass "
                           f"--weights pointing at {_WEIGHTS_HINT[model]}")
    if path.is_dir():
        for name in _CHECKPOINTS[model]:
            if (path / name).is_file():
                return (path / name).resolve()
        hint = ""
        if (path / "config.json").is_file() and '"model_type"' in (path / "config.json").read_text(errors="replace"):
            hint = (" (it looks like a Hugging Face transformers snapshot, whose parameter names timm and "
                    "open_clip do not read)")
        raise FeatureError(f"weights folder {path} holds none of {', '.join(_CHECKPOINTS[model])}{hint}: pass "
                           f"--weights pointing at {_WEIGHTS_HINT[model]}")
    return path.resolve()  # absolute: open_clip would take a bare name like "openai" for a download tag


def _prepare_torchvision(torch) -> None:
    """Make ``import torchvision`` work when its C++ ops cannot load (module docstring).

    Loads ``torchvision/_C.so`` the way torchvision does; when that fails (a CUDA torchvision
    beside a CPU torch), declares the schemas of ``torchvision::nms`` and ``torchvision::qnms``,
    which torchvision's import needs to exist, and says so once.
    """
    global _torchvision_stubs
    if "torchvision" in sys.modules or _torchvision_stubs is not None:
        return
    spec = importlib.util.find_spec("torchvision")
    if spec is None or not spec.submodule_search_locations:
        return  # importing open_clip / timm fails with ImportError, which says to install it
    libs = [p for root in spec.submodule_search_locations for p in sorted(pathlib.Path(root).glob("_C.*"))
            if p.suffix in (".so", ".pyd", ".dylib")]
    error = "no _C library"
    for lib in libs:
        try:
            torch.ops.load_library(str(lib))
            return
        except (OSError, RuntimeError) as e:
            error = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    stubs = torch.library.Library("torchvision", "DEF")
    for op in ("nms", "qnms"):
        try:
            getattr(torch.ops.torchvision, op)
        except (AttributeError, RuntimeError):
            stubs.define(f"{op}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    _torchvision_stubs = stubs
    log.warning("torchvision's C++ ops do not load beside this torch (%s; a CUDA build of torchvision with a "
                "CPU-only torch?): declared torchvision::nms/qnms without kernels so that open_clip and timm "
                "import; torchvision's detection ops are unavailable (feature extraction does not use them)",
                error)


def _require_modules(model: str, modules: Sequence[str]) -> list:
    """Import the optional ``modules`` of ``model`` (torch first), or raise a FeatureError saying how
    to install them."""
    import importlib

    loaded = []
    for mod in modules:
        try:
            if mod != "torch":
                _prepare_torchvision(loaded[0])
            loaded.append(importlib.import_module(mod))
        except ImportError as e:
            raise FeatureError(
                f"model {model!r} needs the optional package {mod!r}, which is not installed "
                f"({e}): install it with `{_INSTALL_HINT[model]}`, or use a built-in model "
                f"({', '.join(BUILT_IN_EXTRACTORS)})") from e
        except RuntimeError as e:  # e.g. torchvision's operator registrations against this torch
            raise FeatureError(
                f"model {model!r}: importing {mod!r} failed ({e}); torch and torchvision must be versions "
                f"that go together: reinstall with `{_INSTALL_HINT[model]}`") from e
    return loaded


def _normalised(img: np.ndarray, mean, std) -> np.ndarray:
    """[h, w, 3] float in [0, 1] → [1, 3, h, w] float32 ``(x − mean) / std``."""
    x = (img - np.asarray(mean, np.float64)) / np.asarray(std, np.float64)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None].astype(np.float32))


class _Clip:
    """open_clip ViT patch tokens, projected into the joint embedding space (no MaskCLIP-style
    modification). The whole image is resized to the model's square input."""

    def __init__(self, model: str, options: dict):
        opts = pop_options(model, options, {"weights": None, "arch": "ViT-B-16", "device": "cpu", "net": None})
        net = opts.pop("net")
        self.opts = opts
        weights = _require_weights("clip", opts["weights"]) if net is None else None
        self.torch, open_clip = _require_modules("clip", ("torch", "open_clip"))
        if net is None:
            net = _load_net("clip", f"open_clip {opts['arch']!r}", weights,
                            lambda: open_clip.create_model(opts["arch"], pretrained=str(weights)))
            self.source = f"open_clip {opts['arch']} patch tokens, weights {weights}"
        else:
            self.source = f"open_clip {type(net).__name__} patch tokens, weights handed over (net=)"
        self.visual = getattr(net, "visual", net).eval().to(opts["device"])
        self.visual.output_tokens = True
        size = self.visual.image_size
        self.input = size if isinstance(size, int) else int(size[0])
        cfg = getattr(self.visual, "preprocess_cfg", None) or {}
        self.mean, self.std = tuple(cfg.get("mean", OPENAI_MEAN)), tuple(cfg.get("std", OPENAI_STD))

    def __call__(self, view: View, size):
        """→ [h, w, D] float32: the g×g token grid resized to the image aspect (long side g) or
        to ``size`` = (w, h)."""
        torch = self.torch
        x = torch.from_numpy(_normalised(resized_image(view.image, (self.input, self.input)), self.mean, self.std))
        with torch.no_grad():
            pooled, tokens = self.visual(x.to(self.opts["device"]))
            proj = getattr(self.visual, "proj", None)
            if proj is not None and tokens.shape[-1] != pooled.shape[-1]:
                tokens = tokens @ proj
        tokens = tokens[0].float().cpu().numpy()
        g = round(float(np.sqrt(tokens.shape[0])))
        if g * g != tokens.shape[0]:
            raise FeatureError(f"clip: {tokens.shape[0]} patch tokens do not form a square grid "
                               f"({type(self.visual).__name__}); use a ViT architecture")
        grid = tokens.reshape(g, g, -1)
        h, w = view.image.shape[:2]
        return resize_features(grid, size if size is not None else fit_aspect(w, h, g / max(w, h)))


def _load_net(model: str, what: str, weights, create):
    """``create()`` (an open_clip/timm constructor reading ``weights``); FeatureError naming the file on failure."""
    try:
        return create()
    except Exception as e:  # noqa: BLE001 — torch/open_clip/timm raise anything on a bad file (AssertionError…)
        raise FeatureError(f"cannot load {what} from {weights} ({type(e).__name__}: {str(e)[:300]}); "
                           f"pass --weights pointing at {_WEIGHTS_HINT[model]}") from e


class _Dinov2:
    """DINOv2 patch tokens (last layer, after the final norm) of a timm ViT; the image keeps its
    aspect, its long side resized to ``input_size`` (a multiple of the patch, 14)."""

    def __init__(self, model: str, options: dict):
        opts = pop_options(model, options, {"weights": None, "arch": "vit_small_patch14_dinov2",
                                            "input_size": 448, "device": "cpu", "net": None})
        net = opts.pop("net")
        self.opts = opts
        weights = _require_weights("dinov2", opts["weights"]) if net is None else None
        self.torch, timm = _require_modules("dinov2", ("torch", "timm"))
        if net is None:
            net = _load_net("dinov2", f"timm {opts['arch']!r}", weights,
                            lambda: timm.create_model(opts["arch"], pretrained=True, dynamic_img_size=True,
                                                      pretrained_cfg_overlay={"file": str(weights)}))
            self.source = f"DINOv2 {opts['arch']} last-layer patch tokens (timm), weights {weights}"
        else:
            self.source = f"DINOv2 {type(net).__name__} last-layer patch tokens (timm), weights handed over (net=)"
        self.net = net.eval().to(opts["device"])
        patch = self.net.patch_embed.patch_size
        self.patch = int(patch if isinstance(patch, int) else patch[0])
        self.skip = int(getattr(self.net, "num_prefix_tokens", 1))  # class token + registers

    def __call__(self, view: View, size):
        """→ [gh, gw, D] float32 patch tokens, or area-resized to ``size`` = (w, h)."""
        torch = self.torch
        h, w = view.image.shape[:2]
        s = self.opts["input_size"] / max(h, w)
        gh = max(1, round(h * s / self.patch))
        gw = max(1, round(w * s / self.patch))
        x = torch.from_numpy(_normalised(resized_image(view.image, (gw * self.patch, gh * self.patch)),
                                         IMAGENET_MEAN, IMAGENET_STD))
        with torch.no_grad():
            out = self.net.forward_features(x.to(self.opts["device"]))
        if out.ndim != 3 or out.shape[1] != self.skip + gh * gw:
            raise FeatureError(f"dinov2: expected {self.skip} + {gh}x{gw} tokens, got {tuple(out.shape)}; "
                               "a net handed over must be a timm ViT built with dynamic_img_size=True")
        grid = out[0, self.skip:].float().cpu().numpy().reshape(gh, gw, -1)
        return resize_features(grid, (gw, gh) if size is None else (int(size[0]), int(size[1])))


PRETRAINED = {"clip": _Clip, "dinov2": _Dinov2}  # model name → extractor class


def clip_text_encoder(weights=None, *, arch: str = "ViT-B-16", device: str = "cpu", net=None):
    """``encode(text) -> [D] float32``: open_clip's text embedding, in the joint space of the clip patch tokens.

    For text queries against a rendered clip feature field (``cusgs-view --clip``): the same LOCAL
    weights as the clip extractor (``weights`` a checkpoint file or its folder, loaded by
    ``open_clip.create_model(arch, pretrained=FILE)``), or ``net=`` an already built open_clip CLIP
    model. The tokenizer is ``open_clip.get_tokenizer(arch)`` (open_clip's bundled BPE vocabulary for
    the OpenAI-style architectures; nothing is downloaded).

    Raises:
      FeatureError: the extra is missing, or the weights are missing or do not load (file named).
    """
    torch, open_clip = _require_modules("clip", ("torch", "open_clip"))
    if net is None:
        weights = _require_weights("clip", weights)
        net = _load_net("clip", f"open_clip {arch!r}", weights,
                        lambda: open_clip.create_model(arch, pretrained=str(weights)))
    net = net.eval().to(device)
    context = int(getattr(net, "context_length", 77))
    tokenizer = open_clip.get_tokenizer(arch, context_length=context)

    def encode(text: str) -> np.ndarray:
        with torch.no_grad():
            return net.encode_text(tokenizer([str(text)]).to(device))[0].float().cpu().numpy()

    return encode
