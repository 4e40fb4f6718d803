"""cusgs_jax.extract.scene: extracting built-in feature models over a tiny demo scene, and the
lock-protected ensure_extracted."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.features import FeatureError, feature_dir, load_features
from cusgs_jax.data.loader import load_scene
from cusgs_jax.extract import ensure_extracted, extract_scene, semantic_features, semantic_palette
from cusgs_jax.extract.scene import _model_lock

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)
DIMS = {"daisy": 104, "hog": 36, "gabor": 18, "semantic": 32}


def _loaded(path, **data):
    """The scene as ``cusgs-extract`` loads it: every view, two random points never carved (none are needed)."""
    return load_scene(path, DataConfig(holdout_every=0, random_points=2, carve="none", **data))


def _files(scene, model, names):
    folder = feature_dir(scene, model)
    return {n: np.load(folder / (n.rsplit(".", 1)[0] + ".npy")) for n in names}


@pytest.mark.parametrize("model", ["daisy", "hog", "gabor", "semantic"])
def test_builtin_extractor_writes_full_maps_deterministically(demo, names, model):
    s = extract_scene(_loaded(demo), model, overwrite=True, progress=False)
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
    extract_scene(_loaded(demo), model, overwrite=True, progress=False)
    again = _files(demo, model, names)
    for n in names:
        np.testing.assert_array_equal(files[n], again[n])


def test_resolution_and_float32(demo, names):
    s = extract_scene(_loaded(demo), "daisy", resolution=(20, 15), dtype="float32", overwrite=True, progress=False)
    assert s.resolution == (20, 15) and s.dtype == "float32"
    arr = _files(demo, "daisy", names)[names[0]]
    assert arr.shape == (15, 20, 104) and arr.dtype == np.float32
    # Semantic ids are resized by nearest neighbour: 2x upsampling repeats pixels exactly.
    extract_scene(_loaded(demo), "semantic", resolution=(2 * W, 2 * H), overwrite=True, progress=False)
    up = _files(demo, "semantic", names)[names[0]].astype(np.float32)
    ids = np.load(demo / "object_ids" / "view_000.npy")
    expected = semantic_features(np.kron(ids, np.ones((2, 2), int))).astype(np.float16)
    np.testing.assert_array_equal(up, expected.astype(np.float32))


def test_existing_features_need_overwrite(demo):
    extract_scene(_loaded(demo), "hog", overwrite=True, progress=False)
    with pytest.raises(FeatureError, match="already exist.*--overwrite"):
        extract_scene(_loaded(demo), "hog", progress=False)


def test_ensure_extracted_skips_complete_and_replaces_partial_sets(demo, names):
    extract_scene(_loaded(demo), "gabor", overwrite=True, progress=False)
    meta = feature_dir(demo, "gabor") / "meta.json"
    stamp = meta.stat().st_mtime_ns
    scene = _loaded(demo)
    assert ensure_extracted(scene, "gabor", progress=False) is False
    assert meta.stat().st_mtime_ns == stamp  # untouched
    meta.unlink()  # an interrupted extraction: files but no meta.json
    assert ensure_extracted(scene, "gabor", progress=False) is True
    assert load_features(demo, "gabor", names, image_size=(W, H)).maps.shape == (V, H, W, DIMS["gabor"])


def test_extraction_lock_is_exclusive_across_open_files(demo):
    import fcntl

    with _model_lock(demo, "gabor"):
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
    code = ("import sys; from cusgs_jax.config import DataConfig; from cusgs_jax.data.loader import load_scene; "
            "from cusgs_jax.extract import ensure_extracted; "
            "scene = load_scene(sys.argv[1], DataConfig(holdout_every=0, random_points=2, carve='none')); "
            "print(ensure_extracted(scene, 'semantic', progress=False))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(scene)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err for _, err in results]
    assert sorted(out.strip() for out, _ in results) == ["False", "True"]
    names = _loaded(scene).names
    assert load_features(scene, "semantic", names).maps.shape[0] == 3


def test_bad_model_and_options(demo):
    with pytest.raises(FeatureError, match="unknown feature model 'sift'.*daisy"):
        extract_scene(_loaded(demo), "sift", progress=False)
    with pytest.raises(FeatureError, match="option.*sigma.*not supported by model 'daisy'"):
        extract_scene(_loaded(demo), "daisy", sigma=2, overwrite=True, progress=False)
    with pytest.raises(FeatureError, match="resolution"):
        extract_scene(_loaded(demo), "daisy", resolution=(0, 3), overwrite=True, progress=False)


def test_semantic_features_follow_object_ids(demo, names):
    extract_scene(_loaded(demo), "semantic", overwrite=True, progress=False)
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
    np.testing.assert_array_equal(semantic_palette()[5],
                                  semantic_features(np.array([[0, 5]]))[0, 1])
    assert not semantic_features(np.zeros((2, 2), np.uint8)).any()


def test_semantic_needs_object_ids(demo, tmp_path):
    plain = tmp_path / "plain"
    shutil.copytree(demo, plain, ignore=shutil.ignore_patterns("object_ids", "features"))
    with pytest.raises(FeatureError, match="only available for the built-in demo scene") as e:
        extract_scene(_loaded(plain), "semantic", progress=False)
    assert str(plain / "object_ids") in str(e.value)
    # An unfinished extraction leaves no meta.json, so nothing half-written gets loaded.
    assert not (feature_dir(plain, "semantic") / "meta.json").exists()
