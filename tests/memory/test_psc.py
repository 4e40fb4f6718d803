"""PSC banks: the chunked build equals the plain greedy reference exactly."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.memory import psc
from cusgs_jax.testing.psc_reference import build_reference


def assert_same(fast: psc.PSCBank, ref: psc.PSCBank):
    assert fast.count == ref.count
    np.testing.assert_array_equal(fast.indices, ref.indices)
    np.testing.assert_array_equal(fast.entries, ref.entries)
    assert fast.entries.dtype == np.float32 and fast.entries.shape == ref.entries.shape
    assert fast.truncated == ref.truncated
    assert fast.gamma == ref.gamma


def duplicate_heavy(seed=0, rows=120, dim=8, bases=6):
    """Repeats, power-of-two and other multiples, sign flips and ulp-level perturbations."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(bases, dim)).astype(np.float32)
    pick = rng.integers(0, bases, rows)
    factor = rng.choice(np.float32([1, 1, 1, 2, 0.5, 4, 3, 7, 1e-3, -1, 1e4]), rows)
    x = base[pick] * factor[:, None]
    wiggle = rng.random(rows) < 0.25  # a few ulps: cosines within ~1e-7 of 1
    x[wiggle] = np.nextafter(x[wiggle], np.float32(np.inf) * rng.choice([-1, 1], x[wiggle].shape))
    return x.astype(np.float32)


@pytest.mark.parametrize("dim", [3, 16])
@pytest.mark.parametrize("gamma", [-0.2, 0.5, 0.8, 1.0])
def test_random_matches_reference(dim, gamma):
    x = np.random.default_rng(dim).normal(size=(100, dim)).astype(np.float32)
    ref = build_reference(x, gamma)
    for chunk in (7, 100, 4096):  # boundaries inside, at and beyond the input
        assert_same(psc.build(x, gamma, chunk=chunk), ref)
    assert 0 < ref.count <= 100


@pytest.mark.parametrize("gamma", [1.0, np.nextafter(1.0, 0.0), 0.9999999, 0.99, 0.5])
def test_duplicate_heavy_matches_reference(gamma):
    x = duplicate_heavy()
    ref = build_reference(x, gamma)
    for chunk in (7, 16):
        assert_same(psc.build(x, gamma, chunk=chunk, initial_capacity=4), ref)


def test_near_threshold_pairs_are_exercised():
    """The duplicate-heavy set really has cosines inside the screening band at gamma = 1."""
    x = duplicate_heavy()
    u = x / np.linalg.norm(x.astype(np.float64), axis=1, keepdims=True)
    cos = (u @ u.T)[np.triu_indices(len(x), 1)]
    tol = psc.screen_tolerance(x.shape[1])
    assert np.sum(np.abs(cos - 1.0) < tol) > 50
    assert np.sum(np.abs(cos - 1.0) < 1e-12) > 10  # exactly parallel copies as well


def test_exact_path_is_taken_in_bank_and_chunk(monkeypatch):
    """Near-threshold pairs reach the exact decision both against the bank and inside a chunk."""
    calls = {"bank": 0, "chunk": 0}
    inner = psc._pairs_at_least

    def counting(a_rows, a_sq, ai, b_rows, b_sq, bj, gamma):
        calls["chunk" if a_rows is b_rows else "bank"] += 1
        return inner(a_rows, a_sq, ai, b_rows, b_sq, bj, gamma)

    monkeypatch.setattr(psc, "_pairs_at_least", counting)
    x = duplicate_heavy()
    assert_same(psc.build(x, 1.0, chunk=16), build_reference(x, 1.0))
    assert calls["bank"] > 0 and calls["chunk"] > 0


def test_gamma_one_rejects_only_exact_direction_repeats():
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=(2, 5)).astype(np.float32)
    x = np.stack([v, v, 2 * v, 0.25 * v, w, -v, v + np.float32(1e-3) * w, w])
    bank = psc.build(x, 1.0, chunk=3)
    np.testing.assert_array_equal(bank.indices, [0, 4, 5, 6])
    assert_same(bank, build_reference(x, 1.0))
    # Any gamma above 1 keeps every non-zero row, repeats included.
    assert psc.build(x, 1.5).count == len(x)


def test_zero_rows_are_ignored():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(60, 6)).astype(np.float32)
    with_zeros = np.insert(x, [0, 0, 5, 17, 17, 17, 40, 60], 0.0, axis=0)
    with_zeros[np.flatnonzero(~with_zeros.any(axis=1))[2]] = -0.0  # negative zeros are zeros too
    for gamma in (0.3, 0.9):
        plain, padded = psc.build(x, gamma, chunk=7), psc.build(with_zeros, gamma, chunk=7)
        np.testing.assert_array_equal(padded.entries, plain.entries)
        np.testing.assert_array_equal(with_zeros[padded.indices], padded.entries)
        assert_same(padded, build_reference(with_zeros, gamma))


@pytest.mark.parametrize("shape", [(0, 5), (9, 5), (2, 3, 0, 5)])
def test_empty_and_all_zero(shape):
    x = np.zeros(shape, np.float32)
    for bank in (psc.build(x, 0.8, chunk=4), build_reference(x, 0.8)):
        assert bank.count == 0
        assert bank.entries.shape == (0, 5) and bank.entries.dtype == np.float32
        assert bank.indices.shape == (0,)
        assert not bank.truncated


def test_entries_are_original_vectors():
    x = (np.random.default_rng(5).normal(size=(50, 4)) * 37.0).astype(np.float32)
    bank = psc.build(x, 0.7, chunk=8)
    np.testing.assert_array_equal(bank.entries, x[bank.indices])
    assert not np.allclose(np.linalg.norm(bank.entries, axis=1), 1.0)


def test_bank_grows_beyond_initial_buffer():
    x = np.random.default_rng(6).normal(size=(150, 24)).astype(np.float32)
    bank = psc.build(x, 0.6, chunk=5, initial_capacity=2)
    assert bank.count > 100  # many doublings of a 2-row buffer
    assert_same(bank, build_reference(x, 0.6))


@pytest.mark.parametrize("max_entries", [0, 1, 13, 1000])
def test_max_entries(max_entries):
    x = np.random.default_rng(7).normal(size=(80, 5)).astype(np.float32)
    bank = psc.build(x, 0.7, chunk=6, max_entries=max_entries)
    assert_same(bank, build_reference(x, 0.7, max_entries=max_entries))
    assert bank.count <= max_entries
    assert bank.truncated == (max_entries < psc.build(x, 0.7).count)


def test_input_forms():
    rng = np.random.default_rng(8)
    maps = rng.normal(size=(3, 4, 5, 6))  # [V, H, W, D] float64
    ref = build_reference(maps.reshape(-1, 6).astype(np.float32), 0.5)
    assert_same(psc.build(maps, 0.5, chunk=11), ref)
    assert_same(psc.build(jnp.asarray(maps, jnp.float32), 0.5, chunk=11), ref)
    assert_same(psc.build(maps.astype(np.float16), 0.5), build_reference(maps.astype(np.float16), 0.5))
    bad = maps.copy()
    bad[1, 2, 3, 4] = np.nan
    with pytest.raises(ValueError):
        psc.build(bad, 0.5)
    with pytest.raises(ValueError):
        psc.build(np.full((2, 3), 1e39), 0.5)  # overflows float32
    with pytest.raises(ValueError):
        psc.build(np.ones(4), 0.5)  # not [..., D]


def test_exact_cosine():
    rng = np.random.default_rng(9)
    a, b = rng.normal(size=(2, 33)).astype(np.float32)
    assert psc.exact_cosine(a, a) == 1.0
    assert psc.exact_cosine(a, np.float32(8) * a) == 1.0
    assert psc.exact_cosine(a, np.float32(2.0 ** -20) * a) == 1.0
    assert psc.exact_cosine(a, -a) == -1.0
    assert psc.exact_cosine(a, b) == psc.exact_cosine(b, a)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    naive = a64 @ b64 / math.sqrt((a64 @ a64) * (b64 @ b64))
    assert abs(psc.exact_cosine(a, b) - naive) < 1e-14


def test_screen_tolerance_bounds_float32_cosines():
    rng = np.random.default_rng(10)
    for dim in (3, 64, 512):
        x = rng.normal(size=(40, dim)).astype(np.float32)
        x[1] = x[0] * np.float32(3)
        x[2] = np.nextafter(x[0], np.float32(np.inf))
        u = x / np.linalg.norm(x.astype(np.float64), axis=1, keepdims=True)
        u = u.astype(np.float32)
        f32 = u @ u.T
        err = max(abs(float(f32[i, j]) - psc.exact_cosine(x[i], x[j])) for i in range(40) for j in range(40))
        assert err < psc.screen_tolerance(dim) / 2  # the documented 2x margin


def test_build_per_model_and_gammas():
    assert dict(psc.M3_GAMMAS) == {"clip": 0.80, "siglip": 0.85, "dinov2": 0.75, "seem": 1.0,
                                   "llama3": 1.0, "llamav": 0.60}
    rng = np.random.default_rng(11)
    feats = {"clip": rng.normal(size=(40, 8)), "seem": duplicate_heavy(rows=40)}
    banks = psc.build_per_model(feats, chunk=9)
    for name, bank in banks.items():
        assert bank.gamma == psc.M3_GAMMAS[name]
        assert_same(bank, build_reference(feats[name], psc.M3_GAMMAS[name]))
    custom = psc.build_per_model({"mine": feats["clip"]}, {"mine": 0.1})
    assert custom["mine"].gamma == 0.1
    with pytest.raises(KeyError):
        psc.build_per_model({"unknown": feats["clip"]})


def test_clustered_input_at_scale_keeps_the_scan_invariants():
    """40k x 32 clustered rows at the default chunk (10 chunks, a growing bank; its timing is
    benchmarks/psc_build.py): kept entries are pairwise below gamma and every row is within gamma of one."""
    rng = np.random.default_rng(12)
    centres = rng.normal(size=(50, 32))
    x = (centres[rng.integers(0, 50, 40_000)] + 0.2 * rng.normal(size=(40_000, 32))).astype(np.float32)
    bank = psc.build(x, 0.8)
    np.testing.assert_array_equal(bank.entries, x[bank.indices])
    assert bank.indices[0] == 0 and np.all(np.diff(bank.indices) > 0)
    unit = x.astype(np.float64) / np.linalg.norm(x.astype(np.float64), axis=1, keepdims=True)
    kept = unit[bank.indices]
    among = kept @ kept.T
    np.fill_diagonal(among, -1.0)
    assert among.max() < 0.8 + 1e-9
    nearest = np.max(unit @ kept.T, axis=1)  # a rejected row has a kept entry at cosine >= gamma
    assert nearest.min() >= 0.8 - 1e-9
