"""A tiny feature-field training setup shared by tests/model/test_queries.py and test_field.py."""

from __future__ import annotations

import types

import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, FeatureConfig, FeatureModelConfig, GrowConfig, ModelConfig, TrainOptions
from cusgs_jax.types import Camera
from cusgs_jax.testing.scenes import random_banks, sfm_points

W, H = 32, 24
K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
# distinctive sizes so the jaxpr test can look for them: Q = 17 + 20 = 37 query channels, M = 23 bank entries
MODELS = (FeatureModelConfig("alpha", query_dim=17), FeatureModelConfig("beta", query_dim=20))


def _cfg(features=True, granularity="per_anchor"):
    feats = FeatureConfig(models=MODELS if features else (), sample_pixels=100)
    return Config(train=TrainOptions(iterations=50), features=feats,
                  model=ModelConfig(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8,
                                    query_granularity=granularity),
                  grow=GrowConfig(stats_start=0, start=1000, stop=1000))


def _banks():
    return {name: jnp.asarray(b) for name, b in random_banks({"alpha": (23, 6), "beta": (23, 9)}).items()}


def _batch(features=True, seed=0):
    rng = np.random.default_rng(seed)
    batch = dict(image=jnp.asarray(rng.uniform(0, 1, (H, W, 3)), jnp.float32),
                 camera=Camera(K, jnp.eye(4), W, H), index=jnp.int32(0))
    if features:
        banks = _banks()
        alpha = np.asarray(banks["alpha"])[rng.integers(0, 23, (H, W))]
        alpha[:3] = 0.0  # "no target" rows
        beta = np.asarray(banks["beta"])[rng.integers(0, 23, (H // 2, W // 2))]  # lower resolution
        batch.update(features={"alpha": jnp.asarray(alpha), "beta": jnp.asarray(beta)}, banks=banks)
    return batch


@pytest.fixture(scope="session")
def feature_scene():
    """``cfg(features, granularity)``, ``points()``, ``banks()``, ``batch(features, seed)`` and the sizes."""
    return types.SimpleNamespace(cfg=_cfg, points=sfm_points, banks=_banks, batch=_batch, W=W, H=H, K=K,
                                 models=MODELS)
