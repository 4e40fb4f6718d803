"""cusgs-extract: built-in dense extractors on a tiny demo scene, the CLI, optional models."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil

import numpy as np
import pytest

from cusgs_jax import extract as ex
from cusgs_jax.data.colmap import load_scene
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.features import FeatureError, feature_dir, load_features

W, H, V = 40, 30, 4
DIMS = {"daisy": 104, "hog": 36, "gabor": 18, "semantic": 32}


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A tiny demo scene (module-wide; tests write features with overwrite=True)."""
    return generate_demo_scene(tmp_path_factory.mktemp("demo"), num_views=V, width=W, height=H,
                               num_points=1500)


@pytest.fixture(scope="module")
def names(demo):
    return load_scene(demo, holdout_every=0).names


def _files(scene, model, names):
    folder = feature_dir(scene, model)
    return {n: np.load(folder / (n.rsplit(".", 1)[0] + ".npy")) for n in names}


# --------------------------------------------------------------------------------------------
# Built-in extractors over a scene
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["daisy", "hog", "gabor", "semantic"])
def test_builtin_extractor_writes_full_maps_deterministically(demo, names, model):
    s = ex.extract(demo, model, overwrite=True, progress=False)
    d = DIMS[model]
    assert (s.model, s.num_views, s.dim, s.resolution, s.dtype) == (model, V, d, (W, H), "float16")
    assert s.folder == feature_dir(demo, model) and s.seconds_per_view > 0
    files = _files(demo, model, names)
    for arr in files.values():  # one map per image, covering the whole image, float16
        assert arr.shape == (H, W, d) and arr.dtype == np.float16
    meta = json.loads((s.folder / "meta.json").read_text())
    assert meta["model"] == model and meta["dim"] == d and meta["resolution"] == [W, H]
    assert meta["dtype"] == "float16" and model in meta["source"]
    assert meta["image_size"] == [W, H]

    fs = load_features(demo, model, names, image_size=(W, H))
    assert fs.maps.shape == (V, H, W, d) and fs.maps.dtype == np.float32
    norms = np.linalg.norm(fs.maps, axis=-1)
    assert norms.max() <= 1.0 + 2e-3  # normalised (float16 rounding)
    if model == "semantic":
        assert 0.3 < s.valid_fraction <= 1.0
    else:  # textured scene: (almost) every pixel has a unit descriptor
        assert s.valid_fraction > 0.99 and np.mean(norms > 0.99) > 0.9

    # Deterministic: a second run writes identical files.
    ex.extract(demo, model, overwrite=True, progress=False)
    again = _files(demo, model, names)
    for n in names:
        np.testing.assert_array_equal(files[n], again[n])


def test_resolution_and_float32(demo, names):
    s = ex.extract(demo, "daisy", resolution=(20, 15), dtype="float32", overwrite=True,
                   progress=False)
    assert s.resolution == (20, 15) and s.dtype == "float32"
    arr = _files(demo, "daisy", names)[names[0]]
    assert arr.shape == (15, 20, 104) and arr.dtype == np.float32
    # Semantic ids are resized by nearest neighbour: 2x upsampling repeats pixels exactly.
    ex.extract(demo, "semantic", resolution=(2 * W, 2 * H), overwrite=True, progress=False)
    up = _files(demo, "semantic", names)[names[0]].astype(np.float32)
    ids = np.load(demo / "object_ids" / "view_000.npy")
    expected = ex.semantic_features(np.kron(ids, np.ones((2, 2), int))).astype(np.float16)
    np.testing.assert_array_equal(up, expected.astype(np.float32))


def test_lab_triples_the_dimension(demo):
    img = load_scene(demo, holdout_every=0).images[0]
    for fn, d in [(ex.daisy_features, 104), (ex.hog_features, 36), (ex.gabor_features, 18)]:
        grey, lab = fn(img), fn(img, lab=True)
        assert grey.shape == (H, W, d) and lab.shape == (H, W, 3 * d)
        assert grey.dtype == lab.dtype == np.float32
        assert np.linalg.norm(lab, axis=-1).max() <= 1.0 + 1e-5
        np.testing.assert_array_equal(fn(img, lab=True), lab)  # deterministic


def test_existing_features_need_overwrite(demo):
    ex.extract(demo, "hog", overwrite=True, progress=False)
    with pytest.raises(FeatureError, match="already exist.*--overwrite"):
        ex.extract(demo, "hog", progress=False)


def test_ensure_extracted_skips_complete_and_replaces_partial_sets(demo, names):
    ex.extract(demo, "gabor", overwrite=True, progress=False)
    meta = feature_dir(demo, "gabor") / "meta.json"
    stamp = meta.stat().st_mtime_ns
    assert ex.ensure_extracted(demo, "gabor", progress=False) is False
    assert meta.stat().st_mtime_ns == stamp  # untouched
    meta.unlink()  # an interrupted extraction: files but no meta.json
    assert ex.ensure_extracted(demo, "gabor", progress=False) is True
    assert load_features(demo, "gabor", names, image_size=(W, H)).maps.shape == (V, H, W, DIMS["gabor"])


def test_extraction_lock_is_exclusive_across_open_files(demo):
    import fcntl

    with ex._model_lock(demo, "gabor"):
        lock_path = feature_dir(demo, "gabor").with_name(".gabor.lock")
        with open(lock_path, "a") as other, pytest.raises(BlockingIOError):
            fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
    with open(lock_path, "a") as other:  # released on exit
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)


def test_concurrent_ensure_extracted_extracts_once(tmp_path):
    """Two processes asking for the same features at once (a parallel sweep): both succeed,
    exactly one extracts, and the set is complete."""
    import subprocess
    import sys

    scene = generate_demo_scene(tmp_path / "scene", num_views=3, width=24, height=18, num_points=600)
    code = ("import sys; from cusgs_jax.extract import ensure_extracted; "
            "print(ensure_extracted(sys.argv[1], 'semantic', progress=False))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(scene)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err for _, err in results]
    assert sorted(out.strip() for out, _ in results) == ["False", "True"]
    names = load_scene(scene, holdout_every=0).names
    assert load_features(scene, "semantic", names).maps.shape[0] == 3


def test_bad_model_and_options(demo):
    with pytest.raises(FeatureError, match="unknown feature model 'sift'.*daisy"):
        ex.extract(demo, "sift", progress=False)
    with pytest.raises(FeatureError, match="option.*sigma.*not supported by model 'daisy'"):
        ex.extract(demo, "daisy", sigma=2, overwrite=True, progress=False)
    with pytest.raises(FeatureError, match="resolution"):
        ex.extract(demo, "daisy", resolution=(0, 3), overwrite=True, progress=False)


# --------------------------------------------------------------------------------------------
# The descriptors themselves
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fn", [ex.daisy_features, ex.hog_features, ex.gabor_features])
@pytest.mark.parametrize("lab", [False, True])
def test_flat_image_gives_zero_vectors(fn, lab):
    flat = np.full((20, 24, 3), 137, np.uint8)
    assert not fn(flat, lab=lab).any()  # zero = no target


def test_daisy_matches_skimage_in_the_interior():
    from skimage import data, transform
    from skimage.feature import daisy

    img = (transform.resize(data.astronaut(), (100, 100), anti_aliasing=True) * 255).astype(
        np.uint8)
    ours = ex.daisy_features(img)
    grey = ex._channels(img, False)[0]
    ref = daisy(grey, step=1, radius=7, rings=2, histograms=6, orientations=8,
                normalization="off")  # ref[i, j] is centred on pixel (i + 7, j + 7)
    ref = ref / np.maximum(np.linalg.norm(ref, axis=-1, keepdims=True), 0.02)
    sl = slice(36, 64)  # farther than radius + 4·sigma from any border: no padding effects
    np.testing.assert_allclose(ours[sl, sl], ref[sl.start - 7:sl.stop - 7, sl.start - 7:sl.stop - 7],
                               atol=1e-5)


def test_gabor_matches_skimage_filters_gabor():
    from skimage import data, transform
    from skimage.filters import gabor

    grey = transform.resize(data.camera(), (30, 40), anti_aliasing=True)
    freqs = (0.1, 0.3)
    bank = ex._gabor_bank(freqs, 3, 1.0, zero_mean=False)
    ours = ex._gabor_channel(grey, bank)
    n = 0
    for f in freqs:
        for k in range(3):
            re, im = gabor(grey, f, theta=np.pi * k / 3, bandwidth=1.0, mode="reflect")
            np.testing.assert_allclose(ours[..., n], np.hypot(re, im), atol=1e-10)
            n += 1


def test_hog_blocks_are_centred_on_pixels():
    # A vertical step edge between columns 19 and 20: mirror image (flip + invert) of itself
    # about x = 20.0, so the block at pixel 19 (centre 19.5) mirrors the one at pixel 20
    # (centre 20.5): its left cells equal the other's right cells.
    img = np.zeros((30, 40, 3), np.uint8)
    img[:, 20:] = 255
    f = ex.hog_features(img, cell=4, orientations=9).reshape(30, 40, 2, 2, 9)  # rows, cols
    np.testing.assert_allclose(f[:, 19, :, 0], f[:, 20, :, 1], atol=1e-6)
    np.testing.assert_allclose(f[:, 19, :, 1], f[:, 20, :, 0], atol=1e-6)
    assert np.abs(f[:, 19, :, 0] - f[:, 19, :, 1]).max() > 0.05  # not trivially symmetric
    assert not f[:, :10].any() and not f[:, 30:].any()  # far from the edge: flat, no target


def test_semantic_features_follow_object_ids(demo, names):
    ex.extract(demo, "semantic", overwrite=True, progress=False)
    fs = load_features(demo, "semantic", names)
    palette = {}
    for v, name in enumerate(names):
        ids = np.load(demo / "object_ids" / (name[:-4] + ".npy"))
        assert not fs.maps[v][ids == 0].any() and not fs.valid[v][ids == 0].any()
        for k in np.unique(ids[ids > 0]):
            vecs = fs.maps[v][ids == k]
            np.testing.assert_array_equal(vecs, np.broadcast_to(vecs[0], vecs.shape))
            np.testing.assert_allclose(np.linalg.norm(vecs[0]), 1.0, atol=2e-3)
            if k in palette:  # the same object has the same vector in every view
                np.testing.assert_array_equal(palette[k], vecs[0])
            palette[k] = vecs[0]
    assert len(palette) >= 3
    keys = sorted(palette)
    vecs = np.stack([palette[k] for k in keys])
    cos = vecs @ vecs.T
    assert np.max(cos - np.eye(len(keys)) * cos) < 0.95  # different objects differ
    # Fixed per id, independent of which other ids exist.
    np.testing.assert_array_equal(ex.semantic_palette()[5],
                                  ex.semantic_features(np.array([[0, 5]]))[0, 1])
    assert not ex.semantic_features(np.zeros((2, 2), np.uint8)).any()


def test_semantic_needs_object_ids(demo, tmp_path):
    plain = tmp_path / "plain"
    shutil.copytree(demo, plain, ignore=shutil.ignore_patterns("object_ids", "features"))
    with pytest.raises(FeatureError, match="only available for the built-in demo scene") as e:
        ex.extract(plain, "semantic", progress=False)
    assert str(plain / "object_ids") in str(e.value)
    # An unfinished extraction leaves no meta.json, so nothing half-written gets loaded.
    assert not (feature_dir(plain, "semantic") / "meta.json").exists()


def test_daisy_is_view_consistent(tmp_path):
    """A surface point's descriptors in two neighbouring views (15° apart) are more similar than
    random pairs of pixels (correspondences from the demo scene's exact depth and poses)."""
    views, w, h = 24, 80, 60
    scene_dir = generate_demo_scene(tmp_path / "orbit", num_views=views, width=w, height=h,
                                    num_points=300)
    scene = load_scene(scene_dir, holdout_every=0)
    rng = np.random.default_rng(0)
    for a in (0, 7, 15):
        b = a + 1
        depth_a = np.load(scene_dir / "depth" / f"view_{a:03d}.npy").astype(np.float64)
        depth_b = np.load(scene_dir / "depth" / f"view_{b:03d}.npy").astype(np.float64)
        i, j = np.nonzero(depth_a > 0)
        z = depth_a[i, j]
        K = scene.Ks[a].astype(np.float64)
        cam = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0] * z, (i + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
        va, vb = scene.viewmats[a].astype(np.float64), scene.viewmats[b].astype(np.float64)
        world = (cam - va[:3, 3]) @ va[:3, :3]
        xb = world @ vb[:3, :3].T + vb[:3, 3]
        Kb = scene.Ks[b].astype(np.float64)
        jb = np.floor(Kb[0, 0] * xb[:, 0] / xb[:, 2] + Kb[0, 2]).astype(int)
        ib = np.floor(Kb[1, 1] * xb[:, 1] / xb[:, 2] + Kb[1, 2]).astype(int)
        ok = (xb[:, 2] > 0) & (jb >= 0) & (jb < w) & (ib >= 0) & (ib < h)
        ok[ok] &= np.abs(depth_b[ib[ok], jb[ok]] - xb[ok, 2]) < 0.01 * xb[ok, 2]  # visible in b
        assert ok.sum() > 500
        fa = ex.daisy_features(scene.images[a])[i[ok], j[ok]]
        fb = ex.daisy_features(scene.images[b])[ib[ok], jb[ok]]
        match = np.sum(fa * fb, -1)
        rand = np.sum(fa * fb[rng.permutation(len(fb))], -1)
        assert np.median(match) > np.median(rand) + 0.05
        assert np.mean(match > rand) > 0.8  # measured ≈ 0.93–0.97


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def test_cli(demo, names, capsys):
    assert ex.main([str(demo), "--model", "gabor", "--lab", "--overwrite"]) == 0
    out, err = capsys.readouterr()
    assert "gabor features ->" in out and f"{V} views, {W}x{H}x54 float16" in out
    assert "cusgs-extract gabor" in err  # the progress bar
    assert load_features(demo, "gabor", names).dim == 54

    assert ex.main([str(demo), "--model", "semantic", "--dim", "8", "--resolution", "20", "15",
                    "--dtype", "float32", "--overwrite", "--quiet"]) == 0
    fs = load_features(demo, "semantic", names)
    assert fs.dim == 8 and fs.resolution == (20, 15) and fs.meta["dtype"] == "float32"
    assert fs.meta["options"] == {"dim": 8, "seed": 0}


def test_cli_errors(demo, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        ex.main([str(tmp_path / "nowhere"), "--model", "daisy", "--quiet"])
    assert e.value.code == 1
    assert "cusgs-extract: error:" in capsys.readouterr().err
    ex.main([str(demo), "--model", "hog", "--overwrite", "--quiet"])
    with pytest.raises(SystemExit) as e:
        ex.main([str(demo), "--model", "hog", "--quiet"])
    assert e.value.code == 1 and "--overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        ex.main([str(demo), "--model", "semantic", "--lab"])
    assert e.value.code == 2 and "--lab applies to" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        ex.main([str(demo), "--model", "sift"])
    assert e.value.code == 2


# --------------------------------------------------------------------------------------------
# Optional foundation-model extractors
# --------------------------------------------------------------------------------------------

_DEPS = {"clip": ("torch", "open_clip"), "dinov2": ("torch", "transformers")}


def _have(*modules):
    return all(importlib.util.find_spec(m) is not None for m in modules)


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_need_local_weights(demo, model):
    with pytest.raises(FeatureError, match="needs local weights: pass --weights PATH") as e:
        ex.extract(demo, model, overwrite=True, progress=False)
    assert "Nothing is ever downloaded" in str(e.value) and "pip install torch" in str(e.value)
    with pytest.raises(FeatureError, match="not found"):
        ex.extract(demo, model, weights=demo / "no_such_weights.bin", overwrite=True,
                   progress=False)


@pytest.mark.parametrize("model", ["clip", "dinov2"])
def test_foundation_models_without_packages_say_how_to_install(demo, model, tmp_path):
    if _have(*_DEPS[model]):
        pytest.skip(f"{' and '.join(_DEPS[model])} are installed")
    weights = tmp_path / "weights.bin"
    weights.write_bytes(b"")
    with pytest.raises(FeatureError, match="optional package") as e:
        ex.extract(demo, model, weights=weights, overwrite=True, progress=False)
    assert ex._INSTALL_HINT[model] in str(e.value)


def test_clip_with_local_weights(demo, names):
    pytest.importorskip("torch")
    pytest.importorskip("open_clip")
    weights = os.environ.get("CUSGS_CLIP_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_CLIP_WEIGHTS to a local open_clip ViT-B-16 checkpoint")
    s = ex.extract(demo, "clip", weights=weights, arch=os.environ.get("CUSGS_CLIP_ARCH",
                                                                      "ViT-B-16"),
                   overwrite=True, progress=False)
    fs = load_features(demo, "clip", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99


def test_dinov2_with_local_weights(demo, names):
    pytest.importorskip("torch")
    pytest.importorskip("transformers")
    weights = os.environ.get("CUSGS_DINOV2_WEIGHTS")
    if not weights:
        pytest.skip("set CUSGS_DINOV2_WEIGHTS to a local DINOv2 Hugging Face snapshot folder")
    s = ex.extract(demo, "dinov2", weights=weights, input_size=112, overwrite=True,
                   progress=False)
    fs = load_features(demo, "dinov2", names, image_size=(W, H))
    assert fs.dim == s.dim and fs.valid.mean() > 0.99


def test_semantic_palette_is_orthonormal_up_to_dim_ids():
    table = ex.semantic_palette(dim=32, seed=0, num_ids=40)
    first = table[1:33].astype(np.float64)
    np.testing.assert_allclose(first @ first.T, np.eye(32), atol=1e-6)
    assert np.all(table[0] == 0)
    np.testing.assert_allclose(np.linalg.norm(table[33:], axis=1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(ex.semantic_palette(dim=32, seed=0, num_ids=10), table[:10])
