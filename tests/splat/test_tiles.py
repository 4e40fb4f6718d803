"""Tile binning against a brute-force per-tile list; the exact ellipse–tile test against the
compositor's own α test and the box binning's renders."""

from __future__ import annotations

import numpy as np
import pytest

import jax
import jax.numpy as jnp
from cusgs_jax.splat import Compositor
from cusgs_jax.splat import render as splat_render
from cusgs_jax.splat.project import project_gaussians
from cusgs_jax.splat.tiles import TileGrid, count_pairs, footprint_rows, intersect_tiles, tile_bounds


def _random_footprints(seed, num, width, height):
    rng = np.random.default_rng(seed)
    means2d = rng.uniform(-20, [width + 20, height + 20], (num, 2)).astype(np.float32)
    radii = np.ceil(rng.uniform(0, 25, (num, 2))).astype(np.float32)
    depths = rng.choice(np.linspace(1, 5, 40), num).astype(np.float32)  # with ties
    visible = rng.uniform(size=num) > 0.2
    return means2d, radii, depths, visible


def _brute_force(means2d, radii, depths, visible, grid):
    order = sorted(np.nonzero(visible)[0], key=lambda g: (depths[g], g))
    box = np.asarray(tile_bounds(jnp.asarray(means2d), jnp.asarray(radii), grid))
    per_tile = [[] for _ in range(grid.num_tiles)]
    for g in order:
        x0, y0, x1, y1 = box[g]
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                per_tile[ty * grid.tiles_x + tx].append(g)
    return per_tile


def test_intersections_match_brute_force_in_depth_order():
    grid = TileGrid(70, 45, 16)
    means2d, radii, depths, visible = _random_footprints(0, 300, 70, 45)
    isect = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, 20000)
    assert int(isect.overflow) == 0
    order = np.asarray(isect.order)
    pairs = np.asarray(isect.pair_gaussians)
    expected = _brute_force(means2d, radii, depths, visible, grid)
    for t in range(grid.num_tiles):
        got = order[pairs[isect.tile_starts[t]:isect.tile_ends[t]]].tolist()
        assert got == expected[t], t
    assert int(isect.num_pairs) == sum(map(len, expected))


@pytest.mark.slow
def test_overflow_drops_the_farthest_pairs_and_counts_them():
    grid = TileGrid(64, 64, 16)
    means2d, radii, depths, visible = _random_footprints(1, 200, 64, 64)
    full = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, 50000)
    cap = int(full.num_pairs) // 2
    small = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, cap)
    assert int(small.num_pairs) == cap
    assert int(small.overflow) == int(full.num_pairs) - cap
    # What survives is the front part of every tile's list.
    order = np.asarray(full.order)
    for t in range(grid.num_tiles):
        a = order[np.asarray(full.pair_gaussians)[full.tile_starts[t]:full.tile_ends[t]]]
        b = order[np.asarray(small.pair_gaussians)[small.tile_starts[t]:small.tile_ends[t]]]
        assert a[: len(b)].tolist() == b.tolist()


# --- the exact ellipse–tile test (footprint_rows) ------------------------------------------------


def _elongated_scene(seed, num, width, height, opacities=(1 / 255 * 1.001, 0.01, 0.1, 0.5, 0.99, 1.0)):
    """Rotated, elongated, anisotropic Gaussians (needles up to ~e^3.5 : 1) of several opacities
    (one just above 1/255, some exactly 1), a few centred off-screen; float32."""
    rng = np.random.default_rng(seed)
    focal = 0.9 * width
    z = rng.uniform(1.0, 6.0, num)
    x = rng.uniform(-0.8, 0.8, num) * z * width / focal
    y = rng.uniform(-0.8, 0.8, num) * z * height / focal
    scales = np.exp(rng.uniform(np.log(0.005), np.log(0.2), (num, 3)))
    scales[:, 0] *= np.exp(rng.uniform(0.0, 3.5, num))
    K = np.array([[focal, 0, width / 2], [0, focal * 1.1, height / 2], [0, 0, 1]])
    scene = dict(means=np.stack([x, y, z], -1), quats=rng.normal(size=(num, 4)), scales=scales,
                 opacities=rng.choice(opacities, num), colors=rng.uniform(0, 1, (num, 3)),
                 viewmat=np.eye(4), K=K)
    return {k: jnp.asarray(v, jnp.float32) for k, v in scene.items()}


def _compositor_tiles(mean, conic, opacity, grid):
    """Tiles with a pixel the compositor draws the Gaussian at, its float32 arithmetic replayed."""
    f32 = np.float32
    py, px = np.mgrid[0:grid.height, 0:grid.width].astype(f32) + f32(0.5)
    dx, dy = f32(mean[0]) - px, f32(mean[1]) - py
    a, b, c = (f32(v) for v in conic)
    sigma = f32(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = np.minimum(f32(0.999), f32(opacity) * np.exp(-np.maximum(sigma, f32(0))))
    rows, cols = np.nonzero((sigma >= 0) & (alpha >= f32(1 / 255)))
    return set(zip((rows // grid.tile_size).tolist(), (cols // grid.tile_size).tolist()))


@pytest.mark.parametrize("tile_size,antialiased", [(8, False), (16, True)])
def test_exact_binning_drops_only_tiles_the_compositor_skips(tile_size, antialiased):
    width, height = 200, 150
    grid = TileGrid(width, height, tile_size)
    s = _elongated_scene(3, 150, width, height)
    proj = project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"],
                             width, height, antialiased=antialiased)
    rows = jax.device_get(footprint_rows(proj.means2d, proj.radii, grid, proj.conics, proj.opacities))
    counts = np.asarray(count_pairs(proj.means2d, proj.radii, proj.visible, grid, proj.conics, proj.opacities))
    box = np.asarray(tile_bounds(proj.means2d, proj.radii, grid))
    means2d, conics, opacities = map(np.asarray, (proj.means2d, proj.conics, proj.opacities))
    visible = np.asarray(proj.visible)
    listed_total = box_total = needed_total = 0
    for g in np.nonzero(visible)[0]:
        listed = set()
        for j in range(rows.cols.shape[1]):
            first = rows.row0[g] + j * rows.step[g]
            for ty in range(first, min(first + rows.step[g], rows.row1[g])):
                listed |= {(ty, tx) for tx in range(rows.col0[g, j], rows.col0[g, j] + rows.cols[g, j])}
        x0, y0, x1, y1 = box[g]
        in_box = {(ty, tx) for ty in range(y0, y1) for tx in range(x0, x1)}
        needed = _compositor_tiles(means2d[g], conics[g], opacities[g], grid) & in_box
        assert counts[g] == len(listed) == rows.ends[g, -1], g
        assert needed <= listed <= in_box, (g, needed - listed)
        listed_total, box_total, needed_total = listed_total + len(listed), box_total + len(in_box), \
            needed_total + len(needed)
    assert not counts[~visible].any()
    assert (rows.step > 1).any()  # Gaussians taller than ROW_GROUPS tile rows have their rows grouped
    # far fewer than the boxes (0.37 and 0.44 of them), close to what the compositor needs (1.14, 1.10 of it:
    # the grouped rows of the tallest needles)
    assert listed_total < 0.5 * box_total and listed_total < 1.2 * needed_total, \
        (box_total, listed_total, needed_total)


def test_exact_binning_pairs_match_its_counts_and_overflow_drops_the_farthest():
    grid = TileGrid(96, 72, 8)
    s = _elongated_scene(4, 200, 96, 72)
    proj = project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"], 96, 72)
    args = (proj.means2d, proj.radii, proj.depths, proj.visible, grid)
    exact = (proj.conics, proj.opacities)
    full = intersect_tiles(*args, 50000, *exact)
    total = int(jnp.sum(count_pairs(proj.means2d, proj.radii, proj.visible, grid, *exact)))
    assert int(full.num_pairs) == total and int(full.overflow) == 0
    assert total < int(intersect_tiles(*args, 50000).num_pairs)
    rows = jax.device_get(footprint_rows(proj.means2d, proj.radii, grid, *exact))
    order, pairs = np.asarray(full.order), np.asarray(full.pair_gaussians)
    for t in range(grid.num_tiles):
        ty, tx = divmod(t, grid.tiles_x)
        got = order[pairs[full.tile_starts[t]:full.tile_ends[t]]]
        for g in got:  # each listed Gaussian lists this tile
            j = (ty - rows.row0[g]) // rows.step[g]
            assert rows.row0[g] <= ty < rows.row1[g] and rows.col0[g, j] <= tx < rows.col0[g, j] + rows.cols[g, j]
        depth = np.asarray(proj.depths)[got]
        assert (np.diff(depth) >= 0).all()
    cap = total // 2
    small = intersect_tiles(*args, cap, *exact)
    assert int(small.num_pairs) == cap and int(small.overflow) == total - cap
    for t in range(grid.num_tiles):
        a = order[pairs[full.tile_starts[t]:full.tile_ends[t]]]
        b = np.asarray(small.order)[np.asarray(small.pair_gaussians)[small.tile_starts[t]:small.tile_ends[t]]]
        assert a[: len(b)].tolist() == b.tolist()


def _box_binning(means2d, radii, depths, visible, grid, max_pairs, conics, opacities):
    """The splatter's binning before the exact test: every tile of the footprint box."""
    return intersect_tiles(means2d, radii, depths, visible, grid, max_pairs)


def _render_both_binnings(monkeypatch, tile_size, antialiased, backend, dtype):
    """(render, gradients) of one random scene with the box binning, then with the exact one: jax.grad of
    a random-cotangent loss of the image and alpha with respect to means, quats, scales, opacities, colors."""
    width, height = 64, 48
    s = {k: v.astype(dtype) for k, v in _elongated_scene(5, 100, width, height).items()}
    keys = ("means", "quats", "scales", "opacities", "colors")
    proj = project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"],
                             width, height, antialiased=antialiased)
    box = intersect_tiles(proj.means2d, proj.radii, proj.depths, proj.visible, TileGrid(width, height, tile_size),
                          20000)
    # one chunk holds a tile's whole list: the JAX compositor then sums each pixel's colour in one
    # pass, and leaving out Gaussians whose α is below 1/255 there adds the same terms in the same order
    longest = int(jnp.max(box.tile_ends - box.tile_starts))
    compositor = Compositor(backend, chunk_size=-(-longest // 8) * 8, tiles="ellipse")
    cotangent = jnp.asarray(np.random.default_rng(6).normal(size=(height, width, 3)), dtype)

    def render(binning):
        monkeypatch.setattr(splat_render, "intersect_tiles", binning)

        def loss(*params):  # traced afresh for each binning (a jit of _rasterize would reuse its trace)
            out = splat_render._rasterize(*params, s["viewmat"], s["K"], width, height, antialiased=antialiased,
                                          tile_size=tile_size, max_pairs=20000, compositor=compositor)
            return jnp.sum(out.image * cotangent) + jnp.sum(out.alpha), out

        (_, out), grads = jax.jit(jax.value_and_grad(loss, argnums=tuple(range(5)), has_aux=True))(
            *(s[k] for k in keys))
        return out, grads

    old, old_grads = render(_box_binning)
    new, new_grads = render(intersect_tiles)
    assert int(new.num_pairs) < 0.8 * int(old.num_pairs) and int(old.overflow) == int(new.overflow) == 0
    for name in ("n_contrib", "hits", "radii", "visible"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
    return old, new, dict(zip(keys, old_grads)), dict(zip(keys, new_grads))


@pytest.mark.parametrize("tile_size,antialiased,backend", [
    (8, False, "jax"), pytest.param(8, True, "jax", marks=pytest.mark.slow), (16, False, "jax"),
    pytest.param(16, True, "jax", marks=pytest.mark.slow), pytest.param(8, True, "pallas", marks=pytest.mark.slow),
])
def test_exact_binning_renders_the_same_image_and_gradients(monkeypatch, tile_size, antialiased, backend):
    old, new, old_grads, new_grads = _render_both_binnings(monkeypatch, tile_size, antialiased, backend,
                                                           jnp.float32)
    for name in ("image", "alpha", "depth"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
    np.testing.assert_allclose(new.significance, old.significance, rtol=1e-6, atol=1e-6)
    for name, b in old_grads.items():
        # The pairs left out add exact zeros, but the compositors sum each Gaussian's per-tile terms with
        # scatter-adds whose order follows the slots (and the JAX one's lane schedule, longest list first):
        # fewer slots change that order, so the gradients agree to float32 rounding, not bit for bit
        # (measured: ≤ 2.2e-5 of the largest entry, after the projection's chain rule; float64 below).
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(new_grads[name], b, rtol=1e-5, atol=1e-4 * scale, err_msg=name)


@pytest.mark.slow  # 43 s: the opt-in binning's float64 check (the float32 one above stays in the default run)
@pytest.mark.parametrize("tile_size,antialiased", [(8, True), (16, False)])
def test_exact_binning_gradients_agree_to_float64_rounding(x64, monkeypatch, tile_size, antialiased):
    old, new, old_grads, new_grads = _render_both_binnings(monkeypatch, tile_size, antialiased, "jax",
                                                           jnp.float64)
    for name in ("image", "alpha", "depth"):  # XLA:CPU sums a chunk's float64 terms in an order the zeros shift
        np.testing.assert_allclose(getattr(new, name), getattr(old, name), rtol=0, atol=1e-14, err_msg=name)
    for name, b in old_grads.items():  # a dropped pixel with α ≥ 1/255 would differ by ~1e-3 of the scale
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(new_grads[name], b, rtol=1e-12, atol=1e-12 * scale, err_msg=name)


@pytest.mark.slow  # 100 s: a 256-Gaussian chunk (one chunk per tile, so the image is bit for bit) compiles slowly
def test_rasterize_bins_by_the_ellipse_only_when_asked():
    """``Compositor(tiles="ellipse")`` (``splat.tiles``) through the public rasterize: fewer pairs, the same image;
    the default is every tile of the box (c806fe4's pairs)."""
    from cusgs_jax.splat import rasterize

    width, height = 64, 48
    s = _elongated_scene(5, 100, width, height)
    args = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")] + [width, height]
    box = rasterize(*args, tile_size=8, compositor=Compositor("jax", chunk_size=256))
    ellipse = rasterize(*args, tile_size=8, compositor=Compositor("jax", chunk_size=256, tiles="ellipse"))
    assert int(ellipse.num_pairs) < 0.8 * int(box.num_pairs)
    np.testing.assert_array_equal(np.asarray(ellipse.image), np.asarray(box.image))
    assert Compositor().tiles == "box"
