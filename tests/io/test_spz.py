"""io/spz.py: SPZ out through gsply, read back by gsply and by PlayCanvas splat-transform, rendered against the PLY."""

from __future__ import annotations

import shutil
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.errors import UserError
from cusgs_jax.eval.metrics import psnr
from cusgs_jax.io import SplatModel, read_ply, render_splats_exact, write_ply
from cusgs_jax.io.spz import read_spz, require_gsply, spz_fractional_bits, write_spz
from cusgs_jax.types import Camera

pytest.importorskip("gsply", reason="the spz extra is not installed (pip install -e '.[spz]')")

# 8-bit colours, alphas, log-scales and SH, 12 fractional bits for positions, smallest-three rotations:
# measured 51.3 and 52.8 dB (seeds 0, 1) against the unquantised model's render. The mistakes a writer
# can make cost far more on these models: f_rest transposed (channel-major) 23.5 and 24.8 dB,
# y and z flipped (RDF read as RUB) 14.5 and 14.7 dB.
MIN_PSNR_DB = 38.0


def _model(seed=0, num=300) -> SplatModel:
    """Gaussians in front of :func:`_camera`, with values inside SPZ's quantisation ranges."""
    rng = np.random.default_rng(seed)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    sh = rng.normal(0.0, 0.15, (num, 16, 3))
    sh[:, 0] = rng.normal(0.0, 0.8, (num, 3))
    return SplatModel(means=f32(rng.normal(0.0, 0.6, (num, 3))), quats=f32(rng.normal(size=(num, 4))),
                      log_scales=f32(rng.normal(-3.0, 0.4, (num, 3))), opacity_logits=f32(rng.normal(0.0, 1.5, num)),
                      sh=f32(sh))


def _camera(width=64, height=48) -> Camera:
    view = np.eye(4, dtype=np.float32)
    view[2, 3] = 3.0  # the origin 3 units in front
    K = np.array([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]], np.float32)
    return Camera(jnp.asarray(K), jnp.asarray(view), width, height)


def _render(model: SplatModel) -> np.ndarray:
    out, _ = render_splats_exact(model, _camera(), background=np.ones(3, np.float32))
    return np.clip(np.asarray(out.image), 0.0, 1.0)


def _unit(q):
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_spz_round_trip_through_gsply_keeps_every_field_and_the_render(tmp_path):
    model = _model()
    path = write_spz(tmp_path / "m.spz", model)
    assert path.stat().st_size < 0.3 * write_ply(tmp_path / "m.ply", model).stat().st_size
    back = read_spz(path)
    assert back.num_gaussians == model.num_gaussians and back.sh_degree == 3
    np.testing.assert_allclose(back.means, model.means, atol=2 ** -12)  # 12 fractional bits
    np.testing.assert_allclose(back.log_scales, model.log_scales, atol=1 / 32 + 1e-6)  # (log σ + 10)·16 in a byte
    dc_limit = 127.5 / (0.15 * 255)  # the DC byte is f_dc·0.15·255 + 127.5: |f_dc| ≤ 3.33 is kept
    np.testing.assert_allclose(back.sh[:, 0], np.clip(model.sh[:, 0], -dc_limit, dc_limit), atol=0.5 / (0.15 * 255) + 1e-6)
    np.testing.assert_allclose(back.sh[:, 1:], np.clip(model.sh[:, 1:], -1, 127 / 128), atol=1 / 256 + 1e-6)
    alpha = lambda logit: 1 / (1 + np.exp(-np.asarray(logit, np.float64)))  # noqa: E731
    np.testing.assert_allclose(alpha(back.opacity_logits), alpha(model.opacity_logits), atol=0.5 / 255 + 1e-6)
    assert np.min(np.abs(np.sum(_unit(back.quats) * _unit(model.quats), axis=1))) > 1 - 1e-4  # q and −q alike
    assert psnr(_render(back), _render(model)) > MIN_PSNR_DB


def test_spz_read_by_splat_transform_renders_as_the_ply(tmp_path):
    """An independent reader: PlayCanvas splat-transform (npm) converts the SPZ to a PLY, read_ply reads it."""
    tool = shutil.which("splat-transform")
    if tool is None:
        pytest.skip("splat-transform is not on PATH (npm install -g @playcanvas/splat-transform)")
    model = _model(seed=1)
    spz = write_spz(tmp_path / "m.spz", model)
    subprocess.run([tool, "-w", str(spz), str(tmp_path / "back.ply")], check=True, capture_output=True, timeout=120)
    other = read_ply(tmp_path / "back.ply")
    ours = read_spz(spz)
    # both readers decode the same bytes: the same Gaussians, in the same order and frame (nothing flipped)
    np.testing.assert_allclose(other.means, ours.means, atol=1e-6)
    np.testing.assert_allclose(other.log_scales, ours.log_scales, atol=1e-5)
    np.testing.assert_allclose(other.sh, ours.sh, atol=1e-5)
    assert np.min(np.abs(np.sum(_unit(other.quats) * _unit(ours.quats), axis=1))) > 1 - 1e-6
    assert psnr(_render(other), _render(model)) > MIN_PSNR_DB


def test_lower_degrees_round_trip(tmp_path):
    model = _model(num=40)
    for degree in (0, 1, 2):
        k = (degree + 1) ** 2
        small = SplatModel(means=model.means, quats=model.quats, log_scales=model.log_scales,
                           opacity_logits=model.opacity_logits, sh=model.sh[:, :k])
        back = read_spz(write_spz(tmp_path / f"d{degree}.spz", small))
        assert back.sh.shape == (40, k, 3)


def test_fractional_bits_shrink_for_far_positions():
    assert spz_fractional_bits(np.zeros((0, 3))) == 12 and spz_fractional_bits(np.array([[2047.0, 0, 0]])) == 12
    assert spz_fractional_bits(np.array([[2048.0, 0, 0]])) == 11
    assert spz_fractional_bits(np.array([[-5000.0, 0, 0]])) == 10  # 5000·2^10 < 2^23 ≤ 5000·2^11
    with pytest.raises(ValueError, match="too large"):
        spz_fractional_bits(np.array([[1e7, 0, 0]]))
    with pytest.raises(ValueError, match="non-finite"):
        spz_fractional_bits(np.array([[np.nan, 0, 0]]))


def test_far_positions_keep_their_precision_relative_to_their_size(tmp_path):
    model = _model(num=20)
    far = SplatModel(means=model.means + np.float32(3000.0), quats=model.quats, log_scales=model.log_scales,
                     opacity_logits=model.opacity_logits, sh=model.sh)
    back = read_spz(write_spz(tmp_path / "far.spz", far))
    np.testing.assert_allclose(back.means, far.means, atol=2 ** -11)  # 11 fractional bits; 12 would wrap around


def test_errors_name_the_file_and_the_fix(tmp_path, monkeypatch):
    with pytest.raises(UserError, match="no such file"):
        read_spz(tmp_path / "missing.spz")
    (tmp_path / "bad.spz").write_bytes(b"not an spz at all")
    with pytest.raises(UserError, match="bad.spz: not a readable SPZ"):
        read_spz(tmp_path / "bad.spz")
    far = _model(num=2)
    far = SplatModel(means=far.means * np.float32(1e7), quats=far.quats, log_scales=far.log_scales,
                     opacity_logits=far.opacity_logits, sh=far.sh)
    with pytest.raises(UserError, match="far.spz: .*too large.*write a .ply"):
        write_spz(tmp_path / "far.spz", far)
    monkeypatch.setitem(sys.modules, "gsply", None)  # as if the extra were not installed
    with pytest.raises(UserError, match=r"x.spz: .*gsply.*pip install 'cusgs-jax\[spz\]'"):
        require_gsply(tmp_path / "x.spz")
    with pytest.raises(UserError, match="gsply"):
        write_spz(tmp_path / "x.spz", _model(num=2))
