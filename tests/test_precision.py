"""Matmul precision (cusgs_jax/precision.py): every geometry ``dot_general`` is at HIGHEST, so a GPU
computes the same numbers as the CPU (TF32 would not be seen in CPU numbers, only in the programs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, DecoderConfig, FeatureConfig, FeatureModelConfig, GrowConfig, ModelConfig
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.model.anchors import AnchorParams
from cusgs_jax.model.bake import bake_anchors, fibonacci_sphere, sh_fit_matrix
from cusgs_jax.model.decode import decode_gaussians, init_decoder
from cusgs_jax.splat import rasterize
from cusgs_jax.splat.lens import Lens
from cusgs_jax.splat.sh import sh_to_rgb
from cusgs_jax.testing.jaxpr_checks import dot_precisions, loose_dots
from cusgs_jax.testing.scenes import make_scene, random_banks, sfm_points
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def _describe(dots) -> str:
    return "; ".join(f"{d.where} {d.shapes} precision={d.precision}" for d in dots)


@pytest.mark.parametrize("channels,lens", [(3, None), (12, None), (3, "OPENCV"), (12, "OPENCV_FISHEYE")])
def test_the_splatter_forward_and_backward_are_at_highest(channels, lens):
    scene = make_scene(seed=1, num=40, channels=channels)
    arrays = [jnp.asarray(scene[k], jnp.float32) for k in ("means", "quats", "scales", "opacities", "colors")]
    cam_lens = None if lens is None else Lens(jnp.asarray([0.05, -0.01, 0.003, -0.001, 0.0, 0.0] if lens != "OPENCV"
                                                          else [-0.12, 0.02, 0.0, 0.0, 0.004, -0.006], jnp.float32),
                                              jnp.asarray([-2.0, 2.0, -2.0, 2.0], jnp.float32), lens != "OPENCV")

    def loss(means, quats, scales, opacities, colors, viewmat):
        out = rasterize(means, quats, scales, opacities, colors, viewmat, jnp.asarray(scene["K"], jnp.float32),
                        scene["width"], scene["height"], lens=cam_lens, antialiased=True)
        return jnp.sum(out.image) + jnp.sum(out.depth)

    viewmat = jnp.asarray(scene["viewmat"], jnp.float32)
    grad = jax.grad(loss, argnums=tuple(range(6)))
    assert dot_precisions(grad, *arrays, viewmat), "the splatter has contractions: the check must see them"
    loose = loose_dots(grad, *arrays, viewmat)
    assert not loose, _describe(loose)


def test_sh_colors_are_at_highest():
    dirs = jnp.asarray(np.random.default_rng(0).normal(size=(7, 3)), jnp.float32)
    coeffs = jnp.ones((7, 16, 3))
    loose = loose_dots(jax.grad(lambda c: jnp.sum(sh_to_rgb(c, dirs, 3))), coeffs)
    assert not loose, _describe(loose)


def _anchor_rows(num=6, n=4, latent=8, seed=0):
    rng = np.random.default_rng(seed)
    params = AnchorParams(offsets=jnp.asarray(rng.normal(size=(num, n, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (num, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(num, latent)), jnp.float32))
    return params, jnp.asarray(rng.uniform(-1, 1, (num, 3)), jnp.float32)


@pytest.mark.parametrize("precision", ["highest", "default"])
def test_the_decoder_heads_follow_model_matmul_precision_and_nothing_else_does(precision):
    cfg = DecoderConfig(n_offsets=4, latent_dim=8, hidden=16, appearance_dim=5, matmul_precision=precision)
    decoder = init_decoder(jax.random.PRNGKey(0), cfg)
    params, centers = _anchor_rows()

    def fn(decoder, params):
        g = decode_gaussians(decoder, params, centers, jnp.ones(6, bool), jnp.zeros(3), jnp.ones(5), cfg)
        return jnp.sum(g.means) + jnp.sum(g.colors) + jnp.sum(g.scales) + jnp.sum(g.opacities)

    dots = dot_precisions(jax.grad(fn, argnums=(0, 1)), decoder, params)
    assert dots
    loose = [d for d in dots if not d.highest]
    if precision == "highest":
        assert not loose, _describe(loose)
    else:  # only the heads' matmuls are relaxed: each sits in nn.py
        assert loose and all(d.where.startswith("nn.py") for d in loose), _describe(loose)


def test_baking_is_at_highest():
    cfg = DecoderConfig(n_offsets=4, latent_dim=8, hidden=16, appearance_dim=0)
    decoder = init_decoder(jax.random.PRNGKey(0), cfg)
    params, centers = _anchor_rows()
    dirs = fibonacci_sphere(16)
    view = np.eye(4, dtype=np.float32)
    view[2, 3] = 3.0
    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], np.float32)

    fit = jnp.asarray(sh_fit_matrix(dirs, 2))

    def fn(params):
        baked = bake_anchors(decoder, params, centers, jnp.ones(6, bool), None, jnp.asarray(dirs), fit, cfg, viewmats=jnp.asarray(view[None]),
                             Ks=jnp.asarray(K[None]), width=32, height=24)
        return baked

    dots = dot_precisions(fn, params)
    assert dots
    loose = [d for d in dots if not d.highest]
    assert not loose, _describe(loose)


@pytest.mark.parametrize("features", [False, True])
def test_the_train_step_is_at_highest_throughout(features):
    """The whole jitted step — decode, queries, splatter, memory attention, losses, gradients, Adam,
    densification statistics — holds no matmul below HIGHEST with the default configuration."""
    models = (FeatureModelConfig("alpha", query_dim=9),) if features else ()
    cfg = Config().replace(
        train=dict(iterations=50), features=FeatureConfig(models=models, sample_pixels=50),
        model=ModelConfig(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
        grow=GrowConfig(stats_start=0, start=5, stop=50, interval=5))
    banks = {name: jnp.asarray(b) for name, b in random_banks({"alpha": (11, 6)}).items()} if features else None
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies, banks)
    W, H = 32, 24
    batch = dict(image=jnp.full((H, W, 3), 0.5), camera=Camera(jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]),
                                                                    jnp.eye(4), W, H), index=jnp.int32(0))
    if features:
        batch.update(features={"alpha": jnp.ones((H, W, 6))}, banks=banks)
    step = make_train_step(cfg, tx, strategies)
    dots = dot_precisions(step, state, batch)
    assert len(dots) > 10
    loose = [d for d in dots if not d.highest]
    assert not loose, _describe(loose)
