"""Feature maps on disk: write/load round trip, validation errors, listing."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cusgs_jax.data.colmap import SceneError
from cusgs_jax.data.features import (
    FeatureError,
    FeatureSet,
    FeatureWriter,
    feature_dir,
    feature_file,
    list_feature_models,
    load_features,
    write_features,
)
from cusgs_jax.testing.scenes import feature_maps

NAMES = ("a.png", "b.png", "c.jpg")


@pytest.fixture
def scene(tmp_path):
    (tmp_path / "images").mkdir()
    return tmp_path


# --------------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["float16", "float32"])
@pytest.mark.parametrize("hw", [(5, 7), (3, 4), (1, 9)])
def test_round_trip(scene, dtype, hw):
    maps = feature_maps(h=hw[0], w=hw[1])
    folder = write_features(scene, "toy", maps, NAMES, source="unit test", dtype=dtype)
    assert folder == feature_dir(scene, "toy") == scene / "features" / "toy"
    for name in NAMES:
        f = feature_file(scene, "toy", name)
        assert f.parent == folder and f.suffix == ".npy"
        assert np.load(f).dtype == np.dtype(dtype)
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["model"] == "toy" and meta["dim"] == 4 and meta["source"] == "unit test"
    assert meta["resolution"] == [hw[1], hw[0]] and meta["dtype"] == dtype

    fs = load_features(scene, "toy", NAMES)
    assert isinstance(fs, FeatureSet)
    assert fs.maps.shape == (3, *hw, 4) and fs.maps.dtype == np.float32
    assert fs.valid.shape == (3, *hw) and fs.valid.dtype == np.bool_
    assert fs.dim == 4 and fs.resolution == (hw[1], hw[0]) and fs.model == "toy"
    assert fs.names == NAMES and fs.num_views == 3 and fs.meta["source"] == "unit test"
    expected = maps.astype(dtype).astype(np.float32)
    np.testing.assert_array_equal(fs.maps, expected)
    np.testing.assert_array_equal(fs.valid, np.any(maps != 0, axis=-1))
    assert not fs.valid[0, 0, 0]
    if hw[0] > 2:
        assert not fs.valid[1, 2].any()


def test_load_follows_requested_order_and_subset(scene):
    maps = feature_maps()
    write_features(scene, "toy", dict(zip(NAMES, maps)), source="dict input")
    fs = load_features(scene, "toy", ["c.jpg", "a.png"])
    np.testing.assert_array_equal(fs.maps, maps[[2, 0]].astype(np.float16).astype(np.float32))


def test_names_with_subfolders(scene):
    maps = feature_maps(n=2)
    write_features(scene, "toy", maps, ["cam0/x.JPG", "cam1/x.JPG"], source="s")
    assert (scene / "features/toy/cam0/x.npy").is_file()
    fs = load_features(scene, "toy", ["cam1/x.JPG"])
    np.testing.assert_array_equal(fs.maps[0], maps[1].astype(np.float16))


def test_overwrite(scene):
    write_features(scene, "toy", feature_maps(), NAMES, source="first")
    with pytest.raises(FeatureError, match="already exist.*overwrite"):
        write_features(scene, "toy", feature_maps(), NAMES, source="second")
    new = feature_maps(n=1, h=2, w=3, d=6, seed=3)
    write_features(scene, "toy", new, ["z.png"], source="second", overwrite=True)
    assert sorted(p.name for p in feature_dir(scene, "toy").iterdir()) == ["meta.json", "z.npy"]
    fs = load_features(scene, "toy", ["z.png"])
    assert fs.dim == 6 and fs.meta["source"] == "second"
    # No temporary files are left behind.
    assert not list(feature_dir(scene, "toy").glob(".*"))


def test_writer_streams_and_meta_last(scene):
    w = FeatureWriter(scene, "stream", source="s", dtype="float32", extra_meta={"k": 1})
    w.start()
    w.write("a.png", np.ones((2, 3, 2)))
    assert not (feature_dir(scene, "stream") / "meta.json").exists()  # not complete yet
    w.write("b.png", np.zeros((2, 3, 2)))
    w.finish()
    meta = json.loads((feature_dir(scene, "stream") / "meta.json").read_text())
    assert meta["k"] == 1 and meta["num_views"] == 2


def test_write_rejects_bad_input(scene):
    with pytest.raises(FeatureError, match="names"):
        write_features(scene, "toy", feature_maps(), None, source="s")
    with pytest.raises(FeatureError, match=r"\[N, h, w, D\]"):
        write_features(scene, "toy", np.zeros((3, 4, 5)), NAMES, source="s")
    with pytest.raises(FeatureError, match="same \\[h, w, D\\]"):
        write_features(scene, "t2", {"a.png": np.ones((2, 2, 3)), "b.png": np.ones((2, 3, 3))},
                       source="s")
    with pytest.raises(FeatureError, match="NaN or Inf"):
        write_features(scene, "t3", {"a.png": np.full((2, 2, 3), np.nan)}, source="s")
    with pytest.raises(FeatureError, match="overflow float16"):
        write_features(scene, "t4", {"a.png": np.full((2, 2, 3), 1e6)}, source="s")
    with pytest.raises(FeatureError, match="same feature file"):
        write_features(scene, "t5", {"a.png": np.ones((2, 2, 3)), "a.jpg": np.ones((2, 2, 3))},
                       source="s")
    with pytest.raises(FeatureError, match="dtype"):
        write_features(scene, "t6", feature_maps(), NAMES, source="s", dtype="float64")
    with pytest.raises(FeatureError, match="not a valid folder name"):
        write_features(scene, "../evil", feature_maps(), NAMES, source="s")
    with pytest.raises(FeatureError, match="relative path"):
        feature_file(scene, "toy", "../x.png")


# --------------------------------------------------------------------------------------------
# Listing
# --------------------------------------------------------------------------------------------


def test_list_feature_models(scene):
    assert list_feature_models(scene) == []
    write_features(scene, "zeta", feature_maps(), NAMES, source="s")
    write_features(scene, "alpha", feature_maps(), NAMES, source="s")
    (scene / "features" / "incomplete").mkdir()  # no meta.json: not listed
    assert list_feature_models(scene) == ["alpha", "zeta"]


# --------------------------------------------------------------------------------------------
# Validation errors: each names the offending file and the fix
# --------------------------------------------------------------------------------------------


def _written(scene, **kw):
    maps = kw.pop("maps", feature_maps())
    folder = write_features(scene, "toy", maps, NAMES, source="s", dtype="float32", **kw)
    return folder


def _set_meta(folder, **changes):
    meta = json.loads((folder / "meta.json").read_text())
    meta.update(changes)
    (folder / "meta.json").write_text(json.dumps(meta))


def test_error_is_a_scene_error(scene):
    assert issubclass(FeatureError, SceneError) and issubclass(FeatureError, ValueError)


def test_error_missing_model_lists_available(scene):
    with pytest.raises(FeatureError, match="no feature models exist"):
        load_features(scene, "clip", NAMES)
    _written(scene)
    with pytest.raises(FeatureError) as e:
        load_features(scene, "clip", NAMES)
    msg = str(e.value)
    assert str(scene / "features" / "clip") in msg and "available models: toy" in msg
    assert "cusgs-extract" in msg


def test_error_missing_meta(scene):
    folder = _written(scene)
    (folder / "meta.json").unlink()
    with pytest.raises(FeatureError, match="meta.json is missing") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "meta.json") in str(e.value) and "interrupted" in str(e.value)


@pytest.mark.parametrize("text,match", [("{not json", "cannot read"), ("[1, 2]", "JSON object")])
def test_error_unreadable_meta(scene, text, match):
    folder = _written(scene)
    (folder / "meta.json").write_text(text)
    with pytest.raises(FeatureError, match=match) as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "meta.json") in str(e.value)


@pytest.mark.parametrize("changes,match", [
    ({"dim": 0}, "dim=0"), ({"dim": "4"}, "dim='4'"), ({"resolution": [7]}, "resolution"),
    ({"resolution": None}, "resolution"),
])
def test_error_bad_meta_fields(scene, changes, match):
    folder = _written(scene)
    _set_meta(folder, **changes)
    with pytest.raises(FeatureError, match=match) as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "meta.json") in str(e.value)


def test_error_meta_dim_disagrees(scene):
    folder = _written(scene)
    _set_meta(folder, dim=8)
    with pytest.raises(FeatureError, match="D=4 but .*dim=8") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "a.npy") in str(e.value)


def test_error_meta_resolution_disagrees(scene):
    folder = _written(scene)
    _set_meta(folder, resolution=[8, 5])
    with pytest.raises(FeatureError, match=r"is 7x5 .* resolution \[8, 5\]") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "a.npy") in str(e.value)


def test_error_missing_view_file(scene):
    folder = _written(scene)
    (folder / "b.npy").unlink()
    with pytest.raises(FeatureError, match="'b.png' is missing") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "b.npy") in str(e.value)


@pytest.mark.parametrize("arr,match", [
    (np.zeros((5, 7), np.float32), r"2 dimensions\); expected \[h, w, D\]"),
    (np.zeros((1, 5, 7, 4), np.float32), "4 dimensions"),
    (np.ones((5, 7, 4), np.int32), "dtype int32"),
    (np.ones((5, 7, 4), bool), "dtype bool"),
])
def test_error_bad_array(scene, arr, match):
    folder = _written(scene)
    np.save(folder / "c.npy", arr)
    with pytest.raises(FeatureError, match=match) as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "c.npy") in str(e.value)


def test_error_unreadable_file(scene):
    folder = _written(scene)
    (folder / "c.npy").write_bytes(b"garbage")
    with pytest.raises(FeatureError, match="cannot read feature map") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "c.npy") in str(e.value)


def test_error_inconsistent_shapes_between_views(scene):
    folder = _written(scene)
    np.save(folder / "b.npy", np.ones((6, 7, 4), np.float32))
    with pytest.raises(FeatureError, match="share one resolution") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "b.npy") in str(e.value) and str(folder / "a.npy") in str(e.value)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_error_non_finite(scene, bad):
    folder = _written(scene)
    arr = np.load(folder / "b.npy")
    arr[1, 2, 3] = bad
    np.save(folder / "b.npy", arr)
    with pytest.raises(FeatureError, match="1 NaN/Inf") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder / "b.npy") in str(e.value)


def test_error_all_zero(scene):
    folder = _written(scene, maps=np.zeros((3, 5, 7, 4), np.float32))
    with pytest.raises(FeatureError, match="all-zero") as e:
        load_features(scene, "toy", NAMES)
    assert str(folder) in str(e.value)


def test_error_aspect_ratio(scene):
    _written(scene)  # 7x5 maps
    load_features(scene, "toy", NAMES, image_size=(70, 50))
    load_features(scene, "toy", NAMES, image_size=(71, 50))  # within 5 %
    with pytest.raises(FeatureError, match="cover the whole image") as e:
        load_features(scene, "toy", NAMES, image_size=(100, 50))
    assert "a.npy" in str(e.value)
