"""cusgs_jax.extract.pretrained: the optional CLIP / DINOv2 extractors (local weights only;
the runs with real weights are skipped unless CUSGS_CLIP_WEIGHTS / CUSGS_DINOV2_WEIGHTS are set)."""

from __future__ import annotations

import importlib.util
import os

import pytest

from cusgs_jax.data.features import FeatureError, load_features
from cusgs_jax.extract import extract
from cusgs_jax.extract.pretrained import _INSTALL_HINT

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)
_DEPS = {"clip": ("torch", "open_clip"), "dinov2": ("torch", "transformers")}


def _have(*modules):
    return all(importlib.util.find_spec(m) is not None for m in modules)


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_need_local_weights(demo, model):
    with pytest.raises(FeatureError, match="needs local weights: pass --weights PATH") as e:
        extract(demo, model, overwrite=True, progress=False)
    assert "Nothing is ever downloaded" in str(e.value) and "pip install torch" in str(e.value)
    with pytest.raises(FeatureError, match="not found"):
        extract(demo, model, weights=demo / "no_such_weights.bin", overwrite=True,
                progress=False)


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_without_packages_say_how_to_install(demo, model, tmp_path):
    if _have(*_DEPS[model]):
        pytest.skip(f"{' and '.join(_DEPS[model])} are installed")
    weights = tmp_path / "weights.bin"
    weights.write_bytes(b"")
    with pytest.raises(FeatureError, match="optional package") as e:
        extract(demo, model, weights=weights, overwrite=True, progress=False)
    assert _INSTALL_HINT[model] in str(e.value)


def test_clip_with_local_weights(demo, names):
    pytest.importorskip("torch")
    pytest.importorskip("open_clip")
    weights = os.environ.get("CUSGS_CLIP_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_CLIP_WEIGHTS to a local open_clip ViT-B-16 checkpoint")
    s = extract(demo, "clip", weights=weights, arch=os.environ.get("CUSGS_CLIP_ARCH", "ViT-B-16"),
                overwrite=True, progress=False)
    fs = load_features(demo, "clip", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99


def test_dinov2_with_local_weights(demo, names):
    pytest.importorskip("torch")
    pytest.importorskip("transformers")
    weights = os.environ.get("CUSGS_DINOV2_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_DINOV2_WEIGHTS to a local DINOv2 Hugging Face snapshot folder")
    s = extract(demo, "dinov2", weights=weights, input_size=112, overwrite=True,
                progress=False)
    fs = load_features(demo, "dinov2", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99
