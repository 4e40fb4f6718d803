"""Image loading: alpha channels composited onto the rendering background (splat.background); empty or
undecodable files named as such."""

from __future__ import annotations

import logging
import pathlib
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

pytest.importorskip("pycolmap")

from cusgs_jax.config import DataConfig  # noqa: E402
from cusgs_jax.data.colmap import SceneError  # noqa: E402
from cusgs_jax.data.loader import load_scene  # noqa: E402
from cusgs_jax.data.images import to_rgb_uint8, check_background  # noqa: E402

BACKGROUND = (0.2, 0.6, 1.0)


@pytest.fixture
def demo_copy(demo, tmp_path):
    """A private copy (images/ + sparse/) of the tiny demo scene, whose images tests replace."""
    for sub in ("images", "sparse"):
        shutil.copytree(demo / sub, tmp_path / sub)
    return tmp_path


def _alpha_pattern(h: int, w: int, seed: int) -> np.ndarray:
    """[h, w] uint8 alpha with fully transparent, fully opaque and partial pixels."""
    alpha = np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)
    alpha[0, :] = 0
    alpha[1, :] = 255
    return alpha


def _composite(rgb: np.ndarray, alpha: np.ndarray, background) -> np.ndarray:
    """Reference: round(rgb·a + 255·bg·(1−a)) in float64 → [H, W, 3] uint8."""
    a = alpha.astype(np.float64)[..., None] / 255.0
    out = rgb.astype(np.float64) * a + 255.0 * np.asarray(background) * (1.0 - a)
    return np.round(out).astype(np.uint8)


def _write_alpha_images(scene: pathlib.Path, names, *, opaque=False) -> dict[str, tuple]:
    """Rewrite images/<name> of ``names`` as RGBA (the RGB kept); returns {name: (rgb, alpha)}."""
    out = {}
    for i, name in enumerate(names):
        rgb = iio.imread(scene / "images" / name)[..., :3]
        alpha = _alpha_pattern(*rgb.shape[:2], seed=i)
        if opaque:
            alpha[:] = 255
        iio.imwrite(scene / "images" / name, np.concatenate([rgb, alpha[..., None]], -1))
        out[name] = (rgb, alpha)
    return out


def _alpha_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "cusgs_jax" and r.levelno == logging.WARNING and "alpha" in r.getMessage()]


def test_rgba_composited_onto_background(demo_copy, caplog):
    names = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0)).names
    written = _write_alpha_images(demo_copy, names)
    with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
        scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0), background=BACKGROUND)
    for i, name in enumerate(scene.names):
        rgb, alpha = written[name]
        np.testing.assert_array_equal(scene.images[i], _composite(rgb, alpha, BACKGROUND))
        np.testing.assert_array_equal(scene.images[i][0], np.broadcast_to([51, 153, 255],
                                                                          rgb[0].shape))
        np.testing.assert_array_equal(scene.images[i][1], rgb[1])  # opaque row: untouched
    (msg,) = _alpha_warnings(caplog)  # one warning per scene
    assert "4 of 4 images" in msg and "4 with transparent pixels" in msg
    assert "(0.2, 0.6, 1)" in msg and "splat.background" in msg


def test_opaque_rgba_equals_rgb(demo_copy, caplog):
    rgb_scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0))
    _write_alpha_images(demo_copy, rgb_scene.names[:2], opaque=True)
    with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
        scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0), background=BACKGROUND)
    np.testing.assert_array_equal(scene.images, rgb_scene.images)
    (msg,) = _alpha_warnings(caplog)
    assert "2 of 4 images" in msg and "0 with transparent pixels" in msg


def test_no_warning_without_alpha(demo_copy, caplog):
    with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
        load_scene(demo_copy, DataConfig(format="colmap"), background=BACKGROUND)
    assert _alpha_warnings(caplog) == []


def test_rgba_composited_before_downscale(demo_copy):
    """Downscaling (2×2 box) averages the composite, not the colour under the alpha."""
    names = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0)).names
    written = _write_alpha_images(demo_copy, names)
    scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0, downscale=2), background=BACKGROUND)
    for i, name in enumerate(scene.names):
        full = _composite(*written[name], BACKGROUND).astype(np.float64)
        h, w = scene.height, scene.width
        box = full.reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
        assert np.max(np.abs(scene.images[i] - box)) <= 0.5 + 1e-9


def test_grey_alpha_composited(demo_copy):
    names = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0)).names
    grey = {}
    for i, name in enumerate(names):
        g = iio.imread(demo_copy / "images" / name)[..., 0]
        alpha = _alpha_pattern(*g.shape, seed=10 + i)
        iio.imwrite(demo_copy / "images" / name, np.stack([g, alpha], -1))  # grey+alpha PNG
        grey[name] = (np.repeat(g[..., None], 3, -1), alpha)
    scene = load_scene(demo_copy, DataConfig(format="colmap", holdout_every=0), background=BACKGROUND)
    for i, name in enumerate(scene.names):
        np.testing.assert_array_equal(scene.images[i], _composite(*grey[name], BACKGROUND))


def test_16bit_alpha_scaled_consistently():
    """uint16 colour and alpha are both read on their 16-bit scale (65535 = 1)."""
    rng = np.random.default_rng(3)
    rgb16 = rng.integers(0, 65536, (5, 6, 3), dtype=np.uint16)
    alpha16 = rng.integers(0, 65536, (5, 6), dtype=np.uint16)
    alpha16[0] = 65535
    alpha16[1] = 0
    out, alpha = to_rgb_uint8(np.concatenate([rgb16, alpha16[..., None]], -1), pathlib.Path("x"),
                               BACKGROUND)
    a = alpha16.astype(np.float64)[..., None] / 65535.0
    expect = rgb16 / 257.0 * a + 255.0 * np.asarray(BACKGROUND) * (1.0 - a)
    np.testing.assert_array_equal(out, np.round(expect).astype(np.uint8))
    np.testing.assert_allclose(alpha, a[..., 0])
    opaque_rgb, no_alpha = to_rgb_uint8(rgb16, pathlib.Path("x"))
    assert no_alpha is None
    np.testing.assert_array_equal(out[0], opaque_rgb[0])  # opaque row = the plain 16-bit RGB
    np.testing.assert_array_equal(out[1], np.broadcast_to([51, 153, 255], (6, 3)))


@pytest.mark.parametrize("bad", [(1.5, 0.0, 0.0), (0.0, 0.0), (-0.1, 0.0, 0.0),
                                 (float("nan"), 0.0, 0.0), "white"])
def test_error_bad_background(demo_copy, bad):
    with pytest.raises(SceneError, match=r"splat\.background=.*three floats in \[0, 1\]"):
        load_scene(demo_copy, DataConfig(format="colmap"), background=bad)


def test_no_background_is_the_layouts_default(demo_copy):
    colmap = DataConfig(format="colmap")
    assert load_scene(demo_copy, colmap, background=None).background == (0.0, 0.0, 0.0)  # COLMAP: black


def test_check_background_accepts_sequences():
    assert check_background([1, 0.5, 0]) == (1.0, 0.5, 0.0)
    assert check_background(np.array([0.1, 0.2, 0.3], np.float32)) == pytest.approx((0.1, 0.2, 0.3))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio probing its legacy plugins
def test_an_empty_or_undecodable_image_is_named_without_a_backend_install_hint(demo_copy):
    path = demo_copy / "images" / "view_001.png"
    good = path.read_bytes()
    path.write_bytes(b"")
    with pytest.raises(SceneError, match=r"image .*view_001\.png is an empty file \(0 bytes\).*replace it with a valid "
                                         r"copy or remove the image from the reconstruction") as raised:
        load_scene(demo_copy, DataConfig(format="colmap"))
    assert "pip install" not in str(raised.value)
    path.write_bytes(good[:300])  # truncated
    with pytest.raises(SceneError, match=r"cannot decode image .*view_001\.png \(300 bytes; .*corrupt or not an image"
                       ) as raised:
        load_scene(demo_copy, DataConfig(format="colmap"))
    assert "pip install" not in str(raised.value)
