"""rasterize() against the float64 reference: forward, gradients, invariances."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.splat import Compositor, check_inputs, rasterize, rasterize_batch
from cusgs_jax.testing.splat_reference import rasterize_reference
from cusgs_jax.testing.scenes import KEYS, as_dtype, make_scene


def _with_stack(scene, count=12, opacity=0.9):
    """Add a stack of opaque Gaussians in front of everything so some pixels hit T ≤ 1e-4."""
    s = dict(scene)
    rng = np.random.default_rng(7)
    view = s["viewmat"]
    cam_pts = np.stack([np.full(count, 0.05), np.full(count, 0.02), np.linspace(0.8, 0.9, count)], -1)
    world = (cam_pts - view[:3, 3]) @ view[:3, :3]
    s["means"] = np.concatenate([s["means"], world])
    s["quats"] = np.concatenate([s["quats"], rng.normal(size=(count, 4))])
    s["scales"] = np.concatenate([s["scales"], np.full((count, 3), 0.12)])
    s["opacities"] = np.concatenate([s["opacities"], np.full(count, opacity)])
    s["colors"] = np.concatenate([s["colors"], rng.uniform(0, 1, (count, s["colors"].shape[1]))])
    return s


def _render(scene, **kw):
    return rasterize(*(jnp.asarray(scene[k]) for k in KEYS), jnp.asarray(scene["viewmat"]),
                     jnp.asarray(scene["K"]), scene["width"], scene["height"], **kw)


def _reference(scene, **kw):
    return rasterize_reference(*(np.asarray(scene[k], np.float64) for k in KEYS),
                               np.asarray(scene["viewmat"], np.float64), np.asarray(scene["K"], np.float64),
                               scene["width"], scene["height"], **kw)


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("channels", [1, 3, 8])
def test_forward_matches_reference(antialiased, channels):
    scene = as_dtype(_with_stack(make_scene(channels, channels=channels, behind=6, offscreen=6, opaque=8)),
                     np.float32)
    out = _render(scene, background=jnp.asarray(scene["background"]), antialiased=antialiased)
    ref = _reference(scene, background=scene["background"].astype(np.float64), antialiased=antialiased)
    # The scene exercises culling, the 0.999 clamp and early termination.
    assert not ref["visible"][:6].any()
    assert (ref["alpha"] >= 0.999).any() and (ref["n_contrib"] > 0).mean() > 0.5
    assert int(out.overflow) == 0
    # float32 against float64: ~50 composited terms of magnitude ≤ 1, eps 6e-8.
    np.testing.assert_allclose(out.image, ref["image"], atol=2e-5)
    np.testing.assert_allclose(out.alpha, ref["alpha"], atol=2e-5)
    np.testing.assert_allclose(out.depth, ref["depth"], atol=2e-5 * 8)
    np.testing.assert_array_equal(out.n_contrib, ref["n_contrib"])
    np.testing.assert_array_equal(out.hits, ref["hits"])
    np.testing.assert_allclose(out.significance, ref["significance"], rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out.visible, ref["visible"])
    np.testing.assert_array_equal(out.radii, ref["radii"])


def test_early_termination_is_exercised():
    scene = as_dtype(_with_stack(make_scene(3), count=12, opacity=0.9), np.float32)
    ref = _reference(scene)
    out = _render(scene)
    # 0.1^4 = 1e-4 ≤ 1e-4: at most 3 of the stacked 0.9-opacity Gaussians get composited.
    stopped = ref["alpha"] > 0.999
    assert stopped.sum() > 5
    np.testing.assert_array_equal(np.asarray(out.n_contrib)[stopped], ref["n_contrib"][stopped])


def _loss_weights(scene, seed=3):
    rng = np.random.default_rng(seed)
    h, w, c = scene["height"], scene["width"], scene["colors"].shape[1]
    return rng.normal(size=(h, w, c)), rng.normal(size=(h, w)), rng.normal(size=(h, w))


def _jax_loss(scene, weights, antialiased=False, lens=None):
    wi, wa, wd = weights

    def loss(means, quats, scales, opacities, colors, background):
        out = rasterize(means, quats, scales, opacities, colors, jnp.asarray(scene["viewmat"]),
                        jnp.asarray(scene["K"]), scene["width"], scene["height"],
                        background=background, antialiased=antialiased, lens=lens)
        return (jnp.sum(out.image * wi) + jnp.sum(out.alpha * wa) + jnp.sum(out.depth * wd))

    return loss


# A strong OPENCV lens and an OPENCV_FISHEYE lens, with trusted boxes wide enough for the scene.
LENSES = {"OPENCV": ([-0.12, 0.02, 0.0, 0.0, 0.004, -0.006], False),
          "OPENCV_FISHEYE": ([0.05, -0.01, 0.003, -0.001, 0.0, 0.0], True)}


@pytest.mark.parametrize("antialiased,lens", [(False, None), (True, None),
                                              pytest.param(False, "OPENCV", marks=pytest.mark.slow),
                                              (True, "OPENCV_FISHEYE")])
def test_gradients_match_finite_differences_float64(x64, antialiased, lens):
    from cusgs_jax.splat.lens import Lens

    scene = make_scene(11, num=40, width=24, height=20, channels=2, behind=2, opaque=3)
    weights = _loss_weights(scene)
    ref_lens = None if lens is None else (np.asarray(LENSES[lens][0]), np.array([-0.9, 0.9, -0.9, 0.9]),
                                          LENSES[lens][1])
    jax_lens = None if lens is None else Lens(jnp.asarray(ref_lens[0]), jnp.asarray(ref_lens[1]), ref_lens[2])
    args = [jnp.asarray(scene[k]) for k in KEYS] + [jnp.asarray(scene["background"])]
    grads = jax.grad(_jax_loss(scene, weights, antialiased, jax_lens), argnums=tuple(range(6)))(*args)
    wi, wa, wd = weights

    def ref_loss(arrays):
        r = rasterize_reference(*arrays[:5], scene["viewmat"], scene["K"], scene["width"], scene["height"],
                                background=arrays[5], antialiased=antialiased, lens=ref_lens)
        return np.sum(r["image"] * wi) + np.sum(r["alpha"] * wa) + np.sum(r["depth"] * wd)

    base = [np.asarray(scene[k], np.float64).copy() for k in KEYS] + [scene["background"].copy()]
    rng = np.random.default_rng(0)
    eps = 1e-6
    for which, grad in enumerate(grads):
        grad = np.asarray(grad).reshape(-1)
        size = base[which].size
        for index in rng.choice(size, min(size, 10), replace=False):
            plus = [a.copy() for a in base]
            plus[which].reshape(-1)[index] += eps
            minus = [a.copy() for a in base]
            minus[which].reshape(-1)[index] -= eps
            fd = (ref_loss(plus) - ref_loss(minus)) / (2 * eps)
            # Central differences: truncation O(eps²·f''') plus rounding 1e-16/eps.
            assert abs(fd - grad[index]) <= 1e-6 + 1e-5 * abs(fd), (KEYS + ("background",))[which]


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_forward_through_a_lens_matches_reference(lens):
    from cusgs_jax.splat.lens import Lens

    scene = as_dtype(make_scene(12, num=150, channels=3, behind=4, offscreen=4, opaque=4), np.float32)
    coeffs, fisheye = LENSES[lens]
    bounds = [-0.8, 0.8, -0.6, 0.6]
    out = _render(scene, background=jnp.asarray(scene["background"]),
                  lens=Lens(jnp.asarray(coeffs, jnp.float32), jnp.asarray(bounds, jnp.float32), fisheye))
    ref = _reference(scene, background=scene["background"].astype(np.float64),
                     lens=(np.asarray(coeffs), np.asarray(bounds), fisheye))
    plain = _reference(scene, background=scene["background"].astype(np.float64))
    assert np.abs(ref["image"] - plain["image"]).max() > 0.1  # the lens changes the picture
    np.testing.assert_allclose(out.image, ref["image"], atol=2e-5)
    np.testing.assert_allclose(out.alpha, ref["alpha"], atol=2e-5)
    np.testing.assert_array_equal(out.visible, ref["visible"])


@pytest.mark.slow
def test_float32_gradients_match_float64():
    scene = make_scene(5, num=150, width=40, height=32, channels=3, behind=3, offscreen=3, opaque=5)
    weights = _loss_weights(scene)
    argnums = tuple(range(6))
    args32 = [jnp.asarray(scene[k], jnp.float32) for k in KEYS] + [jnp.asarray(scene["background"], jnp.float32)]
    g32 = jax.grad(_jax_loss(as_dtype(scene, np.float32), weights), argnums=argnums)(*args32)
    with jax.enable_x64(True):
        args64 = [jnp.asarray(scene[k], jnp.float64) for k in KEYS] + [jnp.asarray(scene["background"], jnp.float64)]
        g64 = jax.grad(_jax_loss(scene, weights), argnums=argnums)(*args64)
        g64 = [np.asarray(g) for g in g64]
    for name, a, b in zip(KEYS + ("background",), g32, g64):
        # Each entry sums O(100) pixel terms; float32 rounding ~1e-6 relative to the largest.
        np.testing.assert_allclose(np.asarray(a), b, atol=2e-4 * np.abs(b).max() + 1e-6, err_msg=name)


@pytest.mark.slow
def test_jit_matches_no_jit():
    scene = as_dtype(make_scene(2, num=30, width=20, height=18, behind=2), np.float32)
    jitted = _render(scene)
    with jax.disable_jit():
        eager = _render(scene)
    for field in ("image", "alpha", "depth", "n_contrib", "significance", "hits"):
        np.testing.assert_allclose(getattr(jitted, field), getattr(eager, field), rtol=1e-5, atol=1e-6, err_msg=field)


def test_permutation_invariance():
    scene = as_dtype(make_scene(4, behind=3, offscreen=3, opaque=4), np.float32)
    perm = np.random.default_rng(0).permutation(len(scene["means"]))
    permuted = dict(scene, **{k: scene[k][perm] for k in KEYS})
    a, b = _render(scene), _render(permuted)
    np.testing.assert_allclose(a.image, b.image, atol=1e-6)
    np.testing.assert_array_equal(a.n_contrib, b.n_contrib)
    np.testing.assert_allclose(np.asarray(a.significance)[perm], b.significance, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(a.hits)[perm], b.hits)


@pytest.mark.slow
def test_zero_opacity_contributes_nothing_and_gets_zero_gradient():
    scene = as_dtype(make_scene(6, num=60), np.float32)
    extra = as_dtype(make_scene(16, num=20), np.float32)
    combined = {k: np.concatenate([scene[k], extra[k]]) for k in KEYS}
    combined["opacities"][60:] = 0.0
    combined = dict(scene, **combined)
    # Same shapes, the extra Gaussians removed by moving them behind the camera:
    # the same program must give bit-identical output.
    removed = dict(combined, means=combined["means"].copy())
    removed["means"][60:] = -(removed["viewmat"][:3, 3] @ removed["viewmat"][:3, :3]) - 1e3 * removed["viewmat"][2, :3]
    a, b = _render(removed), _render(combined)
    for field in ("image", "alpha", "depth", "n_contrib", "hits"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    # a sum over pairs scattered per Gaussian: on a GPU the scatter's order may differ (1 ulp seen on an H200)
    np.testing.assert_allclose(a.significance, b.significance, rtol=1e-6)
    assert not np.asarray(b.visible[60:]).any()
    # Against the scene without them (a differently shaped program): equal to float rounding.
    np.testing.assert_allclose(_render(scene).image, b.image, atol=1e-7)
    weights = _loss_weights(scene)
    args = [jnp.asarray(combined[k]) for k in KEYS] + [jnp.asarray(scene["background"], jnp.float32)]
    grads = jax.grad(_jax_loss(combined, weights), argnums=tuple(range(5)))(*args)
    for name, g in zip(KEYS, grads):
        assert np.all(np.asarray(g)[60:] == 0.0), name
        assert np.all(np.isfinite(np.asarray(g))), name


@pytest.mark.slow
def test_tile_size_and_chunk_do_not_change_the_image():
    scene = as_dtype(make_scene(8, num=200, width=45, height=37), np.float32)
    base = _render(scene)
    for kw in (dict(tile_size=8), dict(tile_size=16, compositor=Compositor("jax", chunk_size=8)),
               dict(tile_size=32, compositor=Compositor("jax", chunk_size=64, lanes=3))):
        other = _render(scene, **kw)
        np.testing.assert_allclose(other.image, base.image, atol=1e-6, err_msg=str(kw))
        np.testing.assert_array_equal(other.n_contrib, base.n_contrib)


def test_overflow_is_reported_not_silent():
    scene = as_dtype(make_scene(9, num=200), np.float32)
    full = _render(scene)
    assert int(full.overflow) == 0
    small = _render(scene, max_pairs=50)
    assert int(small.overflow) == int(full.num_pairs) - 50
    assert int(small.num_pairs) == 50


def test_vmap_batch_equals_single_renders_and_no_recompile(compiles):
    scene = as_dtype(make_scene(10, num=80), np.float32)
    views = np.stack([scene["viewmat"], scene["viewmat"]])
    views[1, :3, 3] += np.array([0.05, -0.03, 0.1], np.float32)
    Ks = np.stack([scene["K"], scene["K"]])
    batch = rasterize_batch(*(jnp.asarray(scene[k]) for k in KEYS), jnp.asarray(views), jnp.asarray(Ks),
                            scene["width"], scene["height"])
    for i in range(2):
        single = _render(dict(scene, viewmat=views[i], K=Ks[i]))
        np.testing.assert_allclose(batch.image[i], single.image, atol=1e-6)
    before = compiles.count("jit(rasterize)")
    moved = dict(scene, means=scene["means"] + np.float32(0.01))
    _render(moved)
    _render(dict(moved, opacities=scene["opacities"] * np.float32(0.5)))
    assert compiles.count("jit(rasterize)") == before  # new values, the same program


def test_check_inputs_accepts_valid_scene():
    scene = as_dtype(make_scene(12, num=10), np.float32)
    check_inputs(*(scene[k] for k in KEYS), scene["viewmat"], scene["K"], scene["width"], scene["height"],
                 background=scene["background"])


def test_zero_gaussians_render_the_background_with_empty_per_gaussian_fields():
    from cusgs_jax.splat import check_inputs, rasterize

    empty = lambda *shape: jnp.zeros((0,) + shape, jnp.float32)  # noqa: E731
    viewmat, K = jnp.eye(4), jnp.array([[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]])
    background = jnp.array([0.2, 0.4, 0.6])
    args = (empty(3), empty(4), empty(3), empty(), empty(3), viewmat, K, 32, 24)
    check_inputs(*args, background=background)  # G = 0 is a valid scene
    out = rasterize(*args, background=background)
    np.testing.assert_array_equal(np.asarray(out.image), np.broadcast_to(np.asarray(background), (24, 32, 3)))
    assert float(jnp.max(out.alpha)) == 0.0 and out.radii.shape == (0, 2) and out.significance.shape == (0,)
    assert int(out.overflow) == 0
    grads = jax.grad(lambda m, c, b: jnp.sum(rasterize(m, args[1], args[2], args[3], c, viewmat, K, 32, 24,
                                                         background=b).image), argnums=(0, 1, 2))(
        args[0], args[4], background)
    assert grads[0].shape == (0, 3) and grads[1].shape == (0, 3)
    np.testing.assert_allclose(np.asarray(grads[2]), 32 * 24, rtol=1e-6)  # d image / d background = T = 1


@pytest.mark.parametrize("change, message", [
    (dict(K=np.eye(2)), r"K must have shape \[3, 3\]"),
    (dict(colors=lambda s: s["colors"][:-1]), r"colors must have shape \[12, 3\]"),
    (dict(means=lambda s: s["means"][:, :2]), r"means must have shape \[G, 3\]"),
    (dict(viewmat=np.eye(3)), r"viewmat must have shape \[4, 4\]"),
    (dict(tile_size=0), "tile_size must be a positive integer, got 0"),
    (dict(tile_size=-8), "tile_size must be a positive integer, got -8"),
    (dict(width=0), "width must be a positive integer"),
])
def test_rasterize_names_a_wrong_argument_instead_of_rendering_a_wrong_image(change, message):
    scene = as_dtype(make_scene(12, num=12), np.float32)
    args = {k: jnp.asarray(scene[k]) for k in (*KEYS, "viewmat", "K")}
    sizes = dict(width=scene["width"], height=scene["height"], tile_size=8)
    for key, value in change.items():
        value = value(scene) if callable(value) else value
        (sizes if key in sizes else args)[key] = jnp.asarray(value) if key in args else value
    with pytest.raises(ValueError, match=message):
        rasterize(*(args[k] for k in (*KEYS, "viewmat", "K")), sizes["width"], sizes["height"],
                  tile_size=sizes["tile_size"])


# --------------------------------------------------------------------------- research code: batch, jit, checks


def _small():
    """A 12-Gaussian scene, float32: the arrays as NumPy (host) and as JAX arrays."""
    scene = as_dtype(make_scene(12, num=12), np.float32)
    host = [scene[k] for k in (*KEYS, "viewmat", "K")]
    return scene, host, [jnp.asarray(a) for a in host]


def _assert_same(a, b):
    for field, x, y in zip(a._fields, a, b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=field)


def test_batch_broadcasts_a_shared_K_and_refuses_one_unbatched_view():
    scene, _, args = _small()
    views = np.stack([scene["viewmat"], scene["viewmat"]])
    views[1, :3, 3] += np.array([0.05, -0.03, 0.1], np.float32)
    K = scene["K"]
    shared = rasterize_batch(*args[:5], jnp.asarray(views), jnp.asarray(K), scene["width"], scene["height"])
    stacked = rasterize_batch(*args[:5], jnp.asarray(views), jnp.asarray(np.stack([K, K])), scene["width"],
                              scene["height"])
    _assert_same(shared, stacked)
    assert shared.image.shape == (2, scene["height"], scene["width"], 3)
    assert not np.array_equal(np.asarray(shared.image[0]), np.asarray(shared.image[1]))  # two views, two images
    with pytest.raises(ValueError, match=r"viewmats must have shape \[B, 4, 4\].*use rasterize\(") as info:
        rasterize_batch(*args[:5], jnp.asarray(views[0]), jnp.asarray(K), scene["width"], scene["height"])
    assert "stack" in str(info.value)
    with pytest.raises(ValueError, match=r"Ks must have shape \[3, 3\] .* or \[2, 3, 3\]"):
        rasterize_batch(*args[:5], jnp.asarray(views), jnp.asarray(np.stack([K, K, K])), scene["width"],
                        scene["height"])


def test_rasterize_jit_is_rasterize_bit_for_bit_and_the_documented_recipe_jits():
    import re

    from cusgs_jax.splat import RASTERIZE_STATIC_ARGNAMES, rasterize_batch_jit, rasterize_jit

    scene, _, args = _small()
    size = (scene["width"], scene["height"])
    eager = rasterize(*args, *size, background=jnp.asarray(scene["background"]), tile_size=8)
    _assert_same(rasterize_jit(*args, *size, background=jnp.asarray(scene["background"]), tile_size=8), eager)
    # the tuple written in rasterize's docstring is the one exported, and jitting with it works
    documented = re.search(r"is\s+#\s+(\(.*?\))\n\n", rasterize.__doc__, re.S).group(1)
    assert eval(documented.replace("#", "")) == RASTERIZE_STATIC_ARGNAMES
    recipe = jax.jit(rasterize, static_argnames=RASTERIZE_STATIC_ARGNAMES)
    _assert_same(recipe(*args, *size, background=jnp.asarray(scene["background"]), tile_size=8), eager)
    # without it: a TypeError saying what to do, not JAX's tracer error
    with pytest.raises(TypeError, match=r"width is a traced value.*rasterize_jit.*RASTERIZE_STATIC_ARGNAMES"):
        jax.jit(rasterize)(*args, *size)
    views, Ks = jnp.stack([args[5], args[5]]), args[6]
    _assert_same(rasterize_batch_jit(*args[:5], views, Ks, *size, tile_size=8),
                 rasterize_batch(*args[:5], views, Ks, *size, tile_size=8))


@pytest.mark.parametrize("host", [True, False], ids=["numpy", "jax"])
@pytest.mark.parametrize("name, index, value, message", [
    ("means", (3, 1), np.nan, r"means has 1 non-finite value\(s\).*index \(3, 1\)"),
    ("means", (0, 2), np.inf, r"means has 1 non-finite"),
    ("scales", (2, 0), -1e-3, r"scales must be non-negative.*index \(2, 0\)"),
    ("scales", (4, 2), np.inf, r"scales has 1 non-finite"),
    ("opacities", (5,), 1.5, r"opacities must lie in \[0, 1\].*1\.5 at index \(5,\)"),
    ("opacities", (0,), -0.01, r"opacities must lie in \[0, 1\]"),
    ("opacities", (7,), np.nan, r"opacities has 1 non-finite"),
])
def test_rasterize_checks_values_outside_jit_naming_the_argument(host, name, index, value, message):
    from cusgs_jax.splat import rasterize_jit

    scene, arrays, _ = _small()
    arrays = [a.copy() for a in arrays]
    arrays[(*KEYS, "viewmat", "K").index(name)][index] = value
    args = arrays if host else [jnp.asarray(a) for a in arrays]
    size = (scene["width"], scene["height"])
    with pytest.raises(ValueError, match=message):
        rasterize(*args, *size)
    with pytest.raises(ValueError, match=message):  # the batch checks the scene once
        rasterize_batch(*args[:5], np.stack([args[5]] * 2), args[6], *size)
    # inside jit the values are traced: nothing checked, the render runs (it is the caller's to check there)
    assert rasterize_jit(*args, *size).image.shape == (scene["height"], scene["width"], 3)
    rasterize(*args, *size, validate=False)


def test_opacities_of_exactly_zero_and_one_and_zero_scales_are_valid():
    scene, arrays, _ = _small()
    arrays = [a.copy() for a in arrays]
    arrays[3][:4], arrays[3][4:8] = 0.0, 1.0
    arrays[2][0] = 0.0
    for args in (arrays, [jnp.asarray(a) for a in arrays]):
        out = rasterize(*args, scene["width"], scene["height"])
        assert np.isfinite(np.asarray(out.image)).all()


def test_means_as_a_python_list_renders_as_the_array_would():
    scene, arrays, args = _small()
    size = (scene["width"], scene["height"])
    _assert_same(rasterize(arrays[0].tolist(), *args[1:], *size), rasterize(*args, *size))
    with pytest.raises(ValueError, match=r"means must have shape \[G, 3\]"):
        rasterize([[0.0, 1.0]], *args[1:], *size)


@pytest.mark.parametrize("max_pairs", [0, -1, 2.5, True])
def test_max_pairs_must_be_a_positive_int(max_pairs):
    from cusgs_jax.splat import rasterize_jit

    scene, _, args = _small()
    for fn in (rasterize, rasterize_jit):  # a static argument: checked under jit too
        with pytest.raises(ValueError, match="max_pairs must be a positive int or None"):
            fn(*args, scene["width"], scene["height"], max_pairs=max_pairs)


@pytest.mark.parametrize("keyword, value", [("backend", "pallas"), ("chunk_size", 8), ("lanes", 2)])
def test_a_removed_keyword_names_its_replacement(keyword, value):
    scene, _, args = _small()
    replacement = rf"compositor=Compositor\({keyword}=\.\.\.\)"
    with pytest.raises(TypeError, match=rf"rasterize\(\) no longer takes {keyword}=; pass {replacement}"):
        rasterize(*args, scene["width"], scene["height"], **{keyword: value})
    with pytest.raises(TypeError, match=rf"rasterize_batch\(\) no longer takes {keyword}="):
        rasterize_batch(*args[:5], args[5][None], args[6], scene["width"], scene["height"], **{keyword: value})
    with pytest.raises(TypeError, match="unexpected keyword argument 'antialias'"):
        rasterize(*args, scene["width"], scene["height"], antialias=True)


def test_the_documented_checkify_recipe_reports_bad_values_inside_jit():
    from jax.experimental import checkify

    scene, _, args = _small()

    def render(means, quats, scales, opacities, colors, viewmat, K):
        checkify.check(jnp.all((opacities >= 0) & (opacities <= 1)), "opacities outside [0, 1]")
        return rasterize(means, quats, scales, opacities, colors, viewmat, K, scene["width"], scene["height"]).image

    checked = jax.jit(checkify.checkify(render, errors=checkify.user_checks | checkify.float_checks))
    err, image = checked(*args)
    err.throw()  # valid inputs: nothing to report
    # checkify's instrumented program is another program: the same image to rounding
    np.testing.assert_allclose(np.asarray(image), np.asarray(rasterize(*args, scene["width"], scene["height"]).image),
                               atol=1e-6)
    err, _ = checked(*args[:3], args[3].at[5].set(1.5), *args[4:])
    with pytest.raises(checkify.JaxRuntimeError, match=r"opacities outside \[0, 1\]"):
        err.throw()
    err, _ = checked(args[0].at[3, 1].set(jnp.nan), *args[1:])
    with pytest.raises(checkify.JaxRuntimeError, match="nan generated"):
        err.throw()
