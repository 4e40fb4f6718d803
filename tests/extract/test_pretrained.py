"""cusgs_jax.extract.pretrained: the optional CLIP (open_clip) / DINOv2 (timm) extractors.

Without downloads: the real architectures (open_clip ViT-B-16, timm vit_small_patch14_dinov2) are
built with random weights inside the tests and run through the extractors' real code — handed
over as ``net=``, and saved to local checkpoint files that the extractors load as they load real
weights. These tests are skipped, saying why, when torch / open_clip / timm (the ``pretrained``
extra) are not installed. Runs with real weights are skipped unless CUSGS_CLIP_WEIGHTS /
CUSGS_DINOV2_WEIGHTS are set."""

from __future__ import annotations

import importlib.util
import json
import os

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.features import FeatureError, feature_dir, load_features
from cusgs_jax.data.loader import load_scene
from cusgs_jax.extract import extract_scene
from cusgs_jax.extract.pretrained import _INSTALL_HINT, _require_modules

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)
_DEPS = {"clip": ("torch", "open_clip"), "dinov2": ("torch", "timm")}


def _loaded(path, **data):
    """The scene as ``cusgs-extract`` loads it: every view, two random points never carved (none are needed)."""
    return load_scene(path, DataConfig(holdout_every=0, random_points=2, carve="none", **data))


def _have(*modules):
    return all(importlib.util.find_spec(m) is not None for m in modules)


def _modules(model):
    """(torch, open_clip | timm), imported as the extractor does (torchvision prepared), or skip."""
    missing = [m for m in _DEPS[model] if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed: the pretrained extra ({_INSTALL_HINT[model]})")
    return _require_modules(model, _DEPS[model])


def _maps(scene, model, names):
    return {n: np.load(feature_dir(scene, model) / (n[:-4] + ".npy")) for n in names}


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_need_local_weights(demo, model):
    with pytest.raises(FeatureError, match="needs local weights: pass --weights PATH") as e:
        extract_scene(_loaded(demo), model, overwrite=True, progress=False)
    assert "Nothing is ever downloaded" in str(e.value) and "pip install -e '.[pretrained]'" in str(e.value)
    with pytest.raises(FeatureError, match="not found"):
        extract_scene(_loaded(demo), model, weights=demo / "no_such_weights.bin", overwrite=True, progress=False)


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_without_packages_say_how_to_install(demo, model, tmp_path):
    if _have(*_DEPS[model]):
        pytest.skip(f"{' and '.join(_DEPS[model])} are installed")
    weights = tmp_path / "weights.bin"
    weights.write_bytes(b"")
    with pytest.raises(FeatureError, match="optional package") as e:
        extract_scene(_loaded(demo), model, weights=weights, overwrite=True, progress=False)
    assert _INSTALL_HINT[model] in str(e.value)


@pytest.mark.slow  # ~14 s: a whole ViT-B/16 on the CPU; in .ci/run's -m slow pass (dinov2's random-weight test stays)
def test_clip_vit_b16_with_random_weights(demo, names):
    """open_clip's ViT-B-16, randomly initialised, through the extractor: token grid → maps."""
    torch, open_clip = _modules("clip")
    torch.manual_seed(0)
    net = open_clip.create_model("ViT-B-16", pretrained=None)
    s = extract_scene(_loaded(demo), "clip", net=net, overwrite=True, progress=False)
    # 14x14 tokens of the 224x224 input; 40x30 at long side 14 would be 14x10 (aspect off 5 %) → 28x21
    assert (s.num_views, s.dim, s.resolution, s.dtype, s.valid_fraction) == (V, 512, (28, 21), "float16", 1.0)
    meta = json.loads((s.folder / "meta.json").read_text())
    assert meta["options"] == {"arch": "ViT-B-16"} and "handed over" in meta["source"]  # no net, weights, device
    fs = load_features(demo, "clip", names, image_size=(W, H))
    assert fs.maps.shape == (V, 21, 28, 512) and np.all(np.isfinite(fs.maps))
    assert fs.maps.std() > 0 and not np.allclose(fs.maps[0], fs.maps[1])  # depends on the image

    # The 14x14 grid itself, against the visual tower run by hand (tokens after ln_post, @ proj).
    s = extract_scene(_loaded(demo), "clip", net=net, resolution=(14, 14), dtype="float32", overwrite=True,
                      progress=False)
    assert s.resolution == (14, 14)
    from skimage import transform

    img = transform.resize(np.asarray(load_image(demo, names[0])) / 255.0, (224, 224, 3), order=1, anti_aliasing=True)
    x = (img - np.array([0.48145466, 0.4578275, 0.40821073])) / np.array([0.26862954, 0.26130258, 0.27577711])
    net.visual.output_tokens = True
    with torch.no_grad():
        _, tokens = net.visual(torch.from_numpy(x.transpose(2, 0, 1)[None].astype(np.float32)))
        expected = (tokens @ net.visual.proj)[0].numpy().reshape(14, 14, 512)
    np.testing.assert_allclose(_maps(demo, "clip", names)[names[0]], expected, rtol=0, atol=1e-4)


def load_image(scene, name):
    import imageio.v3 as iio

    return iio.imread(scene / "images" / name)[..., :3]


_TINY_CLIP = {"embed_dim": 32,
              "vision_cfg": {"image_size": 64, "layers": 2, "width": 64, "head_width": 32, "patch_size": 16},
              "text_cfg": {"context_length": 16, "vocab_size": 1000, "width": 32, "heads": 2, "layers": 1}}


def test_clip_loads_a_local_checkpoint_file(demo, names, tmp_path):
    """The weights=FILE path (open_clip.create_model(arch, pretrained=FILE)) on a tiny ViT config, so the
    checkpoint is small: the maps equal those of the same network handed over."""
    torch, open_clip = _modules("clip")
    config_dir = tmp_path / "configs"
    config_dir.mkdir()
    (config_dir / "cusgs-tiny-vit.json").write_text(json.dumps(_TINY_CLIP))
    open_clip.add_model_config(config_dir)
    torch.manual_seed(1)
    net = open_clip.create_model("cusgs-tiny-vit", pretrained=None)
    folder = tmp_path / "weights"
    folder.mkdir()
    torch.save(net.state_dict(), folder / "open_clip_pytorch_model.bin")

    s = extract_scene(_loaded(demo), "clip", weights=folder, arch="cusgs-tiny-vit", overwrite=True, progress=False)
    assert (s.dim, s.resolution) == (32, (4, 3))  # 4x4 tokens of a 64x64 input → 4x3 (exact aspect)
    assert "open_clip_pytorch_model.bin" in json.loads((s.folder / "meta.json").read_text())["source"]
    from_file = _maps(demo, "clip", names)
    extract_scene(_loaded(demo), "clip", net=net, overwrite=True, progress=False)
    for n, arr in _maps(demo, "clip", names).items():
        np.testing.assert_array_equal(from_file[n], arr)

    with pytest.raises(FeatureError, match="cannot load open_clip 'ViT-B-32'"):  # wrong architecture
        extract_scene(_loaded(demo), "clip", weights=folder / "open_clip_pytorch_model.bin", arch="ViT-B-32",
                      overwrite=True, progress=False)


def test_dinov2_vit_small_with_random_weights_from_a_local_checkpoint(demo, names, tmp_path):
    """timm's vit_small_patch14_dinov2, randomly initialised, saved as a timm checkpoint folder
    (model.safetensors) and loaded by the extractor; the same maps as the network handed over."""
    torch, timm = _modules("dinov2")
    from safetensors.torch import save_file

    torch.manual_seed(0)
    net = timm.create_model("vit_small_patch14_dinov2", pretrained=False, dynamic_img_size=True)
    folder = tmp_path / "vit_small_patch14_dinov2.lvd142m"
    folder.mkdir()
    save_file(net.state_dict(), str(folder / "model.safetensors"))

    s = extract_scene(_loaded(demo), "dinov2", weights=folder, input_size=112, overwrite=True, progress=False)
    # 40x30 → long side 112 → 112x84 = 8x6 patches of 14
    assert (s.num_views, s.dim, s.resolution, s.dtype, s.valid_fraction) == (V, 384, (8, 6), "float16", 1.0)
    meta = json.loads((s.folder / "meta.json").read_text())
    assert meta["options"] == {"arch": "vit_small_patch14_dinov2", "input_size": 112}
    fs = load_features(demo, "dinov2", names, image_size=(W, H))
    assert fs.maps.shape == (V, 6, 8, 384) and np.all(np.isfinite(fs.maps)) and fs.maps.std() > 0
    from_file = _maps(demo, "dinov2", names)
    extract_scene(_loaded(demo), "dinov2", net=net, input_size=112, overwrite=True, progress=False)
    for n, arr in _maps(demo, "dinov2", names).items():
        np.testing.assert_array_equal(from_file[n], arr)

    s = extract_scene(_loaded(demo), "dinov2", net=net, input_size=112, resolution=(20, 15), dtype="float32",
                      overwrite=True, progress=False)
    assert s.resolution == (20, 15) and _maps(demo, "dinov2", names)[names[0]].shape == (15, 20, 384)

    with pytest.raises(FeatureError, match="cannot load timm 'vit_small_patch14_reg4_dinov2'"):
        extract_scene(_loaded(demo), "dinov2", weights=folder, arch="vit_small_patch14_reg4_dinov2",
                      overwrite=True, progress=False)
    hf = tmp_path / "dinov2-small"  # a transformers snapshot: other file and parameter names
    hf.mkdir()
    (hf / "config.json").write_text('{"model_type": "dinov2"}')
    with pytest.raises(FeatureError, match="transformers snapshot"):
        extract_scene(_loaded(demo), "dinov2", weights=hf, overwrite=True, progress=False)


def test_clip_with_local_weights(demo, names):
    _modules("clip")
    weights = os.environ.get("CUSGS_CLIP_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_CLIP_WEIGHTS to a local open_clip ViT-B-16 checkpoint")
    s = extract_scene(_loaded(demo), "clip", weights=weights, arch=os.environ.get("CUSGS_CLIP_ARCH", "ViT-B-16"),
                      overwrite=True, progress=False)
    fs = load_features(demo, "clip", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99


def test_dinov2_with_local_weights(demo, names):
    _modules("dinov2")
    weights = os.environ.get("CUSGS_DINOV2_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_DINOV2_WEIGHTS to a local timm DINOv2 checkpoint (vit_small_patch14_dinov2)")
    s = extract_scene(_loaded(demo), "dinov2", weights=weights,
                      arch=os.environ.get("CUSGS_DINOV2_ARCH", "vit_small_patch14_dinov2"), input_size=112,
                      overwrite=True, progress=False)
    fs = load_features(demo, "dinov2", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99
