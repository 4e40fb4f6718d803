"""composite_tiles_pallas (Pallas's interpreter on the CPU) against the float64 dense oracle and the
pure-JAX compositor: forward and gradients with random cotangents, on empty tiles, opaque tiles
that terminate early, 1 and many channels; and rasterize(backend="pallas") end to end."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.splat import Compositor, rasterize
from cusgs_jax.splat.composite import composite_tiles
from cusgs_jax.splat.composite_pallas import composite_tiles_pallas, padded_channels
from cusgs_jax.splat.render import resolve_backend
from cusgs_jax.splat.tiles import TileGrid
from cusgs_jax.testing.scenes import KEYS, as_dtype, make_scene

# On a GPU the kernels themselves (Triton) are tested; elsewhere Pallas's interpreter runs them.
INTERPRET = jax.default_backend() != "gpu"
GRID = TileGrid(20, 12, 8)  # 3 × 2 tiles, the last column and row partial
PIXELS = GRID.tile_size ** 2


def _dense(means2d, conics, opacities, features):
    """Float64 oracle: every Gaussian at every pixel of the padded grid, depth order = index order,
    with the transmittance stop (a pixel composites nothing once a Gaussian would bring T ≤ 1e-4).

    Returns colours [T, S, C] and final transmittance [T, S] in the tile layout (padding: 0 / 1).
    """
    ts = GRID.tile_size
    tile, s = np.divmod(np.arange(GRID.num_tiles * PIXELS), PIXELS)
    px = (tile % GRID.tiles_x) * ts + s % ts
    py = (tile // GRID.tiles_x) * ts + s // ts
    inside = jnp.asarray((px < GRID.width) & (py < GRID.height))
    dx = means2d[None, :, 0] - (px + 0.5)[:, None]
    dy = means2d[None, :, 1] - (py + 0.5)[:, None]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = jnp.minimum(0.999, opacities * jnp.exp(-sigma))
    alpha = jnp.where((sigma >= 0) & (alpha >= 1 / 255) & inside[:, None], alpha, 0.0)
    after = jnp.cumprod(1 - alpha, axis=1)
    # kept while the running T stays above the stop (T only falls, so this is a prefix)
    alpha = jnp.where(jax.lax.stop_gradient(after) > 1e-4, alpha, 0.0)
    after = jnp.cumprod(1 - alpha, axis=1)
    before = jnp.concatenate([jnp.ones_like(after[:, :1]), after[:, :-1]], axis=1)
    colors = (alpha * before) @ features
    return colors.reshape(GRID.num_tiles, PIXELS, -1), after[:, -1].reshape(GRID.num_tiles, PIXELS)


def _case(kind: str, channels: int, seed: int = 0):
    """Sorted Gaussians and tile lists where every tile lists a prefix of the Gaussians (so the
    oracle, which composites all of them, matches only the tiles that list all) — see ``full``."""
    rng = np.random.default_rng(seed)
    num = 24
    means2d = rng.uniform(0, [GRID.width, GRID.height], (num, 2))
    conics = np.stack([rng.uniform(0.03, 0.4, num), rng.uniform(-0.02, 0.02, num), rng.uniform(0.03, 0.4, num)], -1)
    opacities = rng.uniform(0.05, 0.7, num)
    if kind == "opaque":  # wide, nearly opaque Gaussians in front: every pixel stops early
        conics[:6] = [0.002, 0.0, 0.002]
        opacities[:6] = 0.995
        opacities[6:8] = 1.0  # clamped at 0.999
    features = rng.uniform(-1, 1, (num, channels))
    lengths = np.full(GRID.num_tiles, num)
    if kind == "empty":  # tiles with nothing, and a short list
        lengths[[1, 4]] = 0
        lengths[2] = 5
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int32)
    pairs = np.concatenate([np.arange(n) for n in lengths] + [np.full(7, num - 1)]).astype(np.int32)  # + spare slots
    return tuple(map(jnp.asarray, (means2d, conics, opacities, features))), \
        (jnp.asarray(pairs), jnp.asarray(starts), jnp.asarray(starts + lengths.astype(np.int32))), lengths


def _loss(fn, lists, weights):
    wc, wt = weights

    def loss(*args):
        out = fn(*args, *lists)
        return jnp.sum(out.colors * wc) + jnp.sum(out.transmittance * wt)

    return loss


def _pallas(*args):
    return composite_tiles_pallas(GRID, 3, INTERPRET, *args)


def _jax(*args):
    return composite_tiles(GRID, 4, 2, *args)


@pytest.mark.parametrize("kind,channels", [("plain", 3), ("opaque", 1),
                                           pytest.param("empty", 13, marks=pytest.mark.slow),
                                           pytest.param("opaque", 20, marks=pytest.mark.slow)])  # -m slow: in CI
def test_matches_dense_oracle_and_jax_compositor_float64(x64, kind, channels):
    gaussians, lists, lengths = _case(kind, channels)
    rng = np.random.default_rng(1)
    weights = (jnp.asarray(rng.normal(size=(GRID.num_tiles, PIXELS, channels))),
               jnp.asarray(rng.normal(size=(GRID.num_tiles, PIXELS))))
    ours, theirs = _pallas(*gaussians, *lists), _jax(*gaussians, *lists)
    assert ours.sparse is None and theirs.sparse is None  # no sparse channels asked for
    for name in ours._fields[:-1]:  # every output, integer counts included
        np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name), rtol=1e-12, atol=1e-12, err_msg=name)
    if kind == "opaque":  # the scene terminates early and clamps
        assert (np.asarray(ours.transmittance) < 1e-3).mean() > 0.5
        assert int(jnp.max(ours.last)) < 24
    full = lengths == gaussians[0].shape[0]  # tiles that list every Gaussian: the oracle's case
    colors, trans = _dense(*gaussians)
    np.testing.assert_allclose(np.asarray(ours.colors)[full], np.asarray(colors)[full], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ours.transmittance)[full], np.asarray(trans)[full], rtol=1e-10,
                               atol=1e-12)

    g_ours = jax.grad(_loss(_pallas, lists, weights), argnums=(0, 1, 2, 3))(*gaussians)
    g_jax = jax.grad(_loss(_jax, lists, weights), argnums=(0, 1, 2, 3))(*gaussians)
    for a, b, name in zip(g_ours, g_jax, ("means2d", "conics", "opacities", "features")):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-11, err_msg=name)
    if full.all():  # the oracle's gradients, where it composites what the tiles list
        mask = jnp.asarray(full)[:, None]

        def dense_loss(*args):
            c, t = _dense(*args)
            return jnp.sum(c * weights[0] * mask[..., None]) + jnp.sum(t * weights[1] * mask)

        g_dense = jax.grad(dense_loss, argnums=(0, 1, 2, 3))(*gaussians)
        for a, b, name in zip(g_ours, g_dense, ("means2d", "conics", "opacities", "features")):
            np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10, err_msg=name)


@pytest.mark.slow
def test_float32_matches_jax_compositor():
    gaussians, lists, _ = _case("opaque", 3, seed=4)
    gaussians = tuple(g.astype(jnp.float32) for g in gaussians)
    rng = np.random.default_rng(2)
    weights = (jnp.asarray(rng.normal(size=(GRID.num_tiles, PIXELS, 3)), jnp.float32),
               jnp.asarray(rng.normal(size=(GRID.num_tiles, PIXELS)), jnp.float32))
    ours, theirs = _pallas(*gaussians, *lists), _jax(*gaussians, *lists)
    np.testing.assert_allclose(ours.colors, theirs.colors, atol=2e-6)
    np.testing.assert_allclose(ours.transmittance, theirs.transmittance, atol=2e-6)
    np.testing.assert_array_equal(ours.n_contrib, theirs.n_contrib)
    g_ours = jax.grad(_loss(_pallas, lists, weights), argnums=(0, 1, 2, 3))(*gaussians)
    g_jax = jax.grad(_loss(_jax, lists, weights), argnums=(0, 1, 2, 3))(*gaussians)
    for a, b in zip(g_ours, g_jax):
        # back to front divides T by (1 − α) where the JAX path multiplies front to back: rounding only
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4 * float(jnp.max(jnp.abs(b))))


def _render(scene, backend, **kw):
    return rasterize(*(jnp.asarray(scene[k]) for k in KEYS), jnp.asarray(scene["viewmat"]),
                     jnp.asarray(scene["K"]), scene["width"], scene["height"], compositor=Compositor(backend), **kw)


@pytest.mark.parametrize("tile_size,channels", [(8, 3), pytest.param(16, 5, marks=pytest.mark.slow)])
def test_rasterize_backends_agree_forward_and_gradients(x64, tile_size, channels):
    scene = make_scene(5, num=60, width=36, height=22, channels=channels, behind=3, offscreen=3, opaque=6)
    background = jnp.asarray(scene["background"])
    kw = dict(background=background, tile_size=tile_size)
    ours, theirs = _render(scene, "pallas", **kw), _render(scene, "jax", **kw)
    for name in ("image", "alpha", "depth", "n_contrib", "significance", "hits", "radii", "num_pairs"):
        np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name), rtol=1e-10, atol=1e-12,
                                   err_msg=name)
    rng = np.random.default_rng(6)
    wi, wa, wd = (jnp.asarray(rng.normal(size=s)) for s in (ours.image.shape, ours.alpha.shape, ours.depth.shape))

    def loss(backend):
        def f(means, quats, scales, opacities, colors):
            out = rasterize(means, quats, scales, opacities, colors, jnp.asarray(scene["viewmat"]),
                            jnp.asarray(scene["K"]), scene["width"], scene["height"], compositor=Compositor(backend), **kw)
            return jnp.sum(out.image * wi) + jnp.sum(out.alpha * wa) + jnp.sum(out.depth * wd)
        return f

    args = [jnp.asarray(scene[k]) for k in KEYS]
    g_ours = jax.grad(loss("pallas"), argnums=tuple(range(5)))(*args)
    g_jax = jax.grad(loss("jax"), argnums=tuple(range(5)))(*args)
    for a, b, name in zip(g_ours, g_jax, KEYS):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10, err_msg=name)


@pytest.mark.slow
def test_vmap_over_views_equals_single_renders():
    scene = as_dtype(make_scene(8, num=40, width=24, height=16), np.float32)
    args = [jnp.asarray(scene[k]) for k in KEYS]
    shifted = np.array(scene["viewmat"])
    shifted[0, 3] += 0.05
    views = jnp.asarray(np.stack([scene["viewmat"], shifted]))

    def one(viewmat):
        return rasterize(*args, viewmat, jnp.asarray(scene["K"]), 24, 16, compositor=Compositor("pallas")).image

    batched = jax.vmap(one)(views)
    for i in range(2):
        np.testing.assert_allclose(batched[i], one(views[i]), atol=1e-6)


def test_backend_choice():
    # the kernels on a GPU (gpu_check.py measured them faster there), the JAX compositor elsewhere
    assert resolve_backend("auto", "gpu") == "pallas" and resolve_backend("auto", "cpu") == "jax"
    assert resolve_backend("auto") == ("pallas" if jax.default_backend() == "gpu" else "jax")
    assert resolve_backend("pallas") == "pallas" and resolve_backend("jax") == "jax"
    with pytest.raises(ValueError, match="backend must be one of"):
        resolve_backend("cuda")
    assert [padded_channels(c) for c in (1, 2, 3, 4, 5, 13, 16, 17)] == [1, 2, 4, 4, 8, 16, 16, 32]


def test_non_power_of_two_tile_is_refused():
    gaussians, lists, _ = _case("plain", 3)
    with pytest.raises(ValueError, match="power-of-two tile size"):
        composite_tiles_pallas(TileGrid(20, 12, 6), 3, INTERPRET, *gaussians, *lists)


def test_the_kernels_lower_through_triton_for_a_gpu_without_one():
    """Lowering for CUDA runs here (jax.export): the kernels stay within what Pallas's Triton lowering accepts
    (power-of-two blocks, supported primitives), forward and backward, checked by the CPU suite."""
    grid = TileGrid(40, 24, 16)
    gaussians, lists = (jnp.zeros((30, 2)), jnp.zeros((30, 3)), jnp.zeros(30), jnp.zeros((30, 5))), \
        (jnp.zeros(400, jnp.int32), jnp.zeros(grid.num_tiles, jnp.int32), jnp.zeros(grid.num_tiles, jnp.int32))

    def value_and_grad(*args):
        def loss(m, c, o, f):
            out = composite_tiles_pallas(grid, 4, False, m, c, o, f, *args[4:])
            return jnp.sum(out.colors) + jnp.sum(out.transmittance) + jnp.sum(out.significance)
        return jax.value_and_grad(loss, argnums=(0, 1, 2, 3))(*args[:4])

    exported = jax.export.export(jax.jit(value_and_grad), platforms=["cuda"], disabled_checks=[
        jax.export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")])(*gaussians, *lists)
    assert exported.mlir_module().count("xla.gpu.triton") == 2  # the forward and the backward kernel


def test_auto_falls_back_to_the_jax_compositor_with_one_warning_when_pallas_triton_is_gone(monkeypatch, caplog):
    import builtins
    import logging

    from cusgs_jax.splat import render as render_module

    real_import = builtins.__import__

    def without_triton(name, globals=None, locals=None, fromlist=(), level=0):
        if name == "jax.experimental.pallas" and fromlist and "triton" in fromlist:
            raise ImportError("cannot import name 'triton' (removed)")
        return real_import(name, globals, locals, fromlist, level)

    render_module.pallas_gpu_available.cache_clear()
    monkeypatch.setattr(builtins, "__import__", without_triton)
    try:
        with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
            assert resolve_backend("auto", "gpu") == "jax" and resolve_backend("auto", "gpu") == "jax"
        assert sum("no Pallas Triton backend" in r.getMessage() for r in caplog.records) == 1  # said once
        assert resolve_backend("pallas", "gpu") == "pallas"  # asked for by name: kept (and fails loudly there)
    finally:
        monkeypatch.undo()
        render_module.pallas_gpu_available.cache_clear()
    assert resolve_backend("auto", "gpu") == "pallas"


def test_the_pallas_compositor_off_a_gpu_says_once_that_it_interprets(caplog):
    import logging

    from cusgs_jax.splat import render as render_module

    render_module._interpreting.cache_clear()
    with caplog.at_level(logging.WARNING, logger="cusgs_jax"):
        assert resolve_backend("pallas", "cpu") == "pallas" and resolve_backend("pallas", "cpu") == "pallas"
    assert sum("Pallas's interpreter" in r.getMessage() for r in caplog.records) == 1
