"""Optional foundation-model extractors: CLIP (open_clip) and DINOv2 (transformers) patch tokens.

=======  ===========  ==========================================================================
model    D            what
=======  ===========  ==========================================================================
clip     model width  open_clip ViT patch tokens, projected into the joint embedding space
dinov2   model width  DINOv2 last-layer patch tokens via transformers
=======  ===========  ==========================================================================

Both need LOCAL weights (``weights=PATH``; nothing is ever downloaded) and optional packages
(torch + open_clip_torch, or torch + transformers). Those are imported only when an extractor is
built, never when this module is imported; :mod:`cusgs_jax.extract.scene` itself imports this
module only when a clip or dinov2 extraction is asked for. The maps are the patch grid (long side
= grid size) or, with ``resolution=(W, H)``, that grid area-resized to [H, W].

The extractors follow the protocol of :mod:`cusgs_jax.extract.scene`: ``cls(model, options)``
with ``.opts`` and ``.source``, called as ``extractor(view, size) -> [h, w, D]``.
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import numpy as np

from cusgs_jax.data.features import FeatureError
from cusgs_jax.data.resize import resize_features
from cusgs_jax.extract.base import BUILT_IN_EXTRACTORS, View, pop_options, resized_image

_INSTALL_HINT = {
    "clip": "pip install torch open_clip_torch",
    "dinov2": "pip install torch transformers",
}
_WEIGHTS_HINT = {
    "clip": ("an open_clip checkpoint file (e.g. open_clip_pytorch_model.bin of "
             "laion/CLIP-ViT-B-16-laion2B-s34B-b88K, with --arch ViT-B-16), copied to this "
             "machine"),
    "dinov2": ("a local Hugging Face snapshot folder of a DINOv2 model (config.json + "
               "model.safetensors, e.g. facebook/dinov2-small), copied to this machine"),
}


def _require_weights(model: str, weights) -> pathlib.Path:
    """The existing local weights path for ``model``, or a FeatureError saying what to pass."""
    if not weights:
        raise FeatureError(
            f"model {model!r} needs local weights: pass --weights PATH (weights=PATH), {model} "
            f"weights being {_WEIGHTS_HINT[model]}. Nothing is ever downloaded. Install the "
            f"optional dependencies with `{_INSTALL_HINT[model]}`.")
    path = pathlib.Path(weights).expanduser()
    if not path.exists():
        raise FeatureError(f"weights for model {model!r} not found: {path} does not exist; pass "
                           f"--weights pointing at {_WEIGHTS_HINT[model]}")
    return path


def _require_modules(model: str, modules: Sequence[str]) -> list:
    """Import the optional ``modules`` of ``model``, or raise a FeatureError saying how to
    install them."""
    import importlib

    loaded = []
    for mod in modules:
        try:
            loaded.append(importlib.import_module(mod))
        except ImportError as e:
            raise FeatureError(
                f"model {model!r} needs the optional package {mod!r}, which is not installed "
                f"({e}): install it with `{_INSTALL_HINT[model]}`, or use a built-in model "
                f"({', '.join(BUILT_IN_EXTRACTORS)})") from e
    return loaded


def _grid_size(size, grid_hw) -> tuple[int, int]:
    """Output (w, h): ``size`` when given, else the patch grid ``grid_hw`` = (gh, gw)."""
    return (int(size[0]), int(size[1])) if size is not None else (grid_hw[1], grid_hw[0])


class _Clip:
    """open_clip ViT patch tokens, projected into the joint embedding space (no MaskCLIP-style
    modification). The whole image is resized to the model's square input."""

    def __init__(self, model: str, options: dict):
        self.opts = pop_options(model, options, {"weights": None, "arch": "ViT-B-16",
                                                  "device": "cpu"})
        weights = _require_weights("clip", self.opts["weights"])
        self.torch, open_clip = _require_modules("clip", ("torch", "open_clip"))
        net, _, _ = open_clip.create_model_and_transforms(self.opts["arch"],
                                                          pretrained=str(weights))
        self.visual = net.visual.eval().to(self.opts["device"])
        self.visual.output_tokens = True
        size = self.visual.image_size
        self.input = size if isinstance(size, int) else int(size[0])
        self.source = f"open_clip {self.opts['arch']} patch tokens, weights {weights}"

    def __call__(self, view: View, size):
        """→ [h, w, D] float32: the g×g token grid resized to the image aspect (long side g) or
        to ``size`` = (w, h)."""
        torch = self.torch
        img = resized_image(view.image, (self.input, self.input))
        mean = np.array([0.48145466, 0.4578275, 0.40821073])
        std = np.array([0.26862954, 0.26130258, 0.27577711])
        x = torch.from_numpy(((img - mean) / std).transpose(2, 0, 1)[None].astype(np.float32))
        with torch.no_grad():
            pooled, tokens = self.visual(x.to(self.opts["device"]))
            proj = getattr(self.visual, "proj", None)
            if proj is not None and tokens.shape[-1] != pooled.shape[-1]:
                tokens = tokens @ proj
        tokens = tokens[0].float().cpu().numpy()
        g = round(float(np.sqrt(tokens.shape[0])))
        grid = tokens.reshape(g, g, -1)
        h, w = view.image.shape[:2]
        default = (g, max(1, round(g * h / w))) if w >= h else (max(1, round(g * w / h)), g)
        return resize_features(grid, size if size is not None else default)


class _Dinov2:
    """DINOv2 patch tokens (last layer) from a local Hugging Face snapshot via transformers; the
    image keeps its aspect, its long side resized to ``input_size`` (a multiple of 14)."""

    def __init__(self, model: str, options: dict):
        self.opts = pop_options(model, options, {"weights": None, "input_size": 448,
                                                  "device": "cpu"})
        weights = _require_weights("dinov2", self.opts["weights"])
        self.torch, transformers = _require_modules("dinov2", ("torch", "transformers"))
        self.net = transformers.AutoModel.from_pretrained(str(weights), local_files_only=True)
        self.net = self.net.eval().to(self.opts["device"])
        self.patch = int(getattr(self.net.config, "patch_size", 14))
        self.skip = 1 + int(getattr(self.net.config, "num_register_tokens", 0) or 0)
        self.source = f"DINOv2 last-layer patch tokens (transformers), weights {weights}"

    def __call__(self, view: View, size):
        """→ [gh, gw, D] float32 patch tokens, or area-resized to ``size`` = (w, h)."""
        torch = self.torch
        h, w = view.image.shape[:2]
        s = self.opts["input_size"] / max(h, w)
        gh = max(1, round(h * s / self.patch))
        gw = max(1, round(w * s / self.patch))
        img = resized_image(view.image, (gw * self.patch, gh * self.patch))
        mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
        x = torch.from_numpy(((img - mean) / std).transpose(2, 0, 1)[None].astype(np.float32))
        with torch.no_grad():
            out = self.net(pixel_values=x.to(self.opts["device"])).last_hidden_state
        grid = out[0, self.skip:].float().cpu().numpy().reshape(gh, gw, -1)
        return resize_features(grid, _grid_size(size, (gh, gw)))


PRETRAINED = {"clip": _Clip, "dinov2": _Dinov2}  # model name → extractor class
