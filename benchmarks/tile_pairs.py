"""Tile pairs and time of the exact ellipse–tile binning against the footprint box; prints JSON.

``splat.tiles.intersect_tiles`` lists a Gaussian only in the tiles its opacity-aware ellipse reaches
(given the conics and opacities, as ``rasterize`` passes them); without them it lists every tile of the
footprint box, as before (docs/rasterizer.md#footprint-and-tiles). Both give the same image, up to the
last bit where the JAX compositor's chunk sums regroup (``image_max_abs_diff``).
For each scene this measures, per view:

* ``pairs``: tile–Gaussian pairs, box and exact (and their ratio);
* ``binning_s``: the binning alone (sort, counts, slots, pair sort) on a fixed projection;
* ``forward_s`` / ``forward_backward_s``: the whole render (projection, binning, compositing) and its
  gradient with respect to the Gaussians, as ``rasterize`` does it.

Box and exact are timed alternately in one process (median of ``--repeats``), on the same inputs.

Scenes: ``random`` — ``benchmarks/scenes.random_scene`` (footprints 3–30 px, random rotations
and anisotropy; ``--elongation`` stretches one axis further, as the tests' needles); ``demo`` —
the demo scene's start model as ``cusgs-train`` builds it (RGB only), its Gaussians decoded at
the first training views (the active ones rendered), pairs counted at every training view.

    python benchmarks/tile_pairs.py                                # random 50k at 256², demo
    python benchmarks/tile_pairs.py --scenes random --gaussians 200000 --size 512
    python benchmarks/tile_pairs.py --scenes random --elongation 2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from scenes import random_scene  # noqa: E402
from timing import median_seconds  # noqa: E402

from cusgs_jax.splat import Compositor  # noqa: E402
from cusgs_jax.splat import render as splat_render  # noqa: E402
from cusgs_jax.splat.project import project_gaussians  # noqa: E402
from cusgs_jax.splat.tiles import TileGrid, count_pairs, intersect_tiles  # noqa: E402

BINNINGS = ("box", "exact")


def _box(means2d, radii, depths, visible, grid, max_pairs, conics=None, opacities=None):
    """The binning before the exact test: every tile of the footprint box."""
    return intersect_tiles(means2d, radii, depths, visible, grid, max_pairs)


@contextlib.contextmanager
def _binning(name):
    """``rasterize``'s binning while a render is traced (box or exact)."""
    saved = splat_render.intersect_tiles
    splat_render.intersect_tiles = _box if name == "box" else intersect_tiles
    try:
        yield
    finally:
        splat_render.intersect_tiles = saved


def _alternately(fns: dict, args, repeats: int) -> dict:
    """{name: median seconds}, the functions timed in turn, ``repeats`` rounds."""
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            times[name].append(median_seconds(fn, args, 1))
    return {name: float(np.median(t)) for name, t in times.items()}


def measure_view(params, viewmat, K, width, height, *, tile_size, antialiased, compositor, repeats):
    """Pairs and times of one view, box against exact, each at the pair capacity training would fit to
    its own count (``1.25 · pairs + 4096``, as ``training/capacity.py`` grows it).

    Args:
      params: (means, quats, scales, opacities, colors) device arrays.
    """
    grid = TileGrid(width, height, tile_size)
    project = jax.jit(lambda *p: project_gaussians(*p[:4], viewmat, K, width, height, antialiased=antialiased))
    proj = project(*params)
    counts = {name: int(jnp.sum(count_pairs(proj.means2d, proj.radii, proj.visible, grid,
                                            *((proj.conics, proj.opacities) if name == "exact" else ()))))
              for name in BINNINGS}
    capacity = {name: int(1.25 * counts[name]) + 4096 for name in BINNINGS}
    binning = {name: jax.jit(lambda pr, name=name: intersect_tiles(
        pr.means2d, pr.radii, pr.depths, pr.visible, grid, capacity[name],
        *((pr.conics, pr.opacities) if name == "exact" else ()))) for name in BINNINGS}
    cotangent = jnp.asarray(np.random.default_rng(0).normal(size=(height, width, params[4].shape[1])), jnp.float32)
    forward, both = {}, {}
    for name in BINNINGS:
        def render(*p, name=name):
            return splat_render._rasterize(*p, viewmat, K, width, height, antialiased=antialiased,
                                           tile_size=tile_size, max_pairs=capacity[name], compositor=compositor)

        def loss(*p, render=render):
            out = render(*p)
            return jnp.sum(out.image * cotangent), out.num_pairs

        with _binning(name):  # traced (and compiled) here, with this binning
            forward[name] = jax.jit(render).lower(*params).compile()
            both[name] = jax.jit(jax.value_and_grad(loss, argnums=tuple(range(5)), has_aux=True)).lower(
                *params).compile()
    outs = {name: forward[name](*params) for name in BINNINGS}
    for name in BINNINGS:
        jax.block_until_ready(binning[name](proj))
        jax.block_until_ready(both[name](*params))
        assert int(outs[name].num_pairs) == counts[name] and int(outs[name].overflow) == 0, name
    images = [np.asarray(outs[name].image) for name in BINNINGS]
    return dict(
        pairs=counts, pair_ratio=round(counts["exact"] / max(counts["box"], 1), 4), capacity=capacity,
        visible=int(jnp.sum(proj.visible)),
        # bit for bit where each tile's list fits one compositor chunk; otherwise the chunk sums regroup
        image_bit_identical=bool(np.array_equal(*images)),
        image_max_abs_diff=float(np.abs(images[0] - images[1]).max()),
        binning_s=_alternately(binning, (proj,), repeats),
        forward_s=_alternately(forward, params, repeats),
        forward_backward_s=_alternately(both, params, repeats),
    )


def random_case(args) -> dict:
    scene = random_scene(args.gaussians, args.size, args.size)
    if args.elongation:  # needles, as tests/splat/test_tiles.py draws them: one axis up to e^elongation longer
        stretch = np.exp(np.random.default_rng(1).uniform(0.0, args.elongation, args.gaussians))
        scene["scales"] = (scene["scales"] * np.stack([stretch, np.ones_like(stretch), np.ones_like(stretch)], -1)
                           ).astype(np.float32)
    params = tuple(jnp.asarray(scene[k]) for k in ("means", "quats", "scales", "opacities", "colors"))
    view = measure_view(params, jnp.asarray(scene["viewmat"]), jnp.asarray(scene["K"]), args.size, args.size,
                        tile_size=args.tile_size, antialiased=False, compositor=Compositor(args.backend),
                        repeats=args.repeats)
    return dict(scene="random", gaussians=args.gaussians, width=args.size, height=args.size,
                tile_size=args.tile_size, elongation=args.elongation, views=[view])


def demo_case(args) -> dict:
    """The demo scene's start model (RGB only, as ``benchmarks/step_profile.py --scene demo`` builds it)."""
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.config import Config, DataConfig
    from cusgs_jax.data.demo import demo_scene_path
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.densify.factory import make_strategies
    from cusgs_jax.model.decode import decode_view
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.types import Camera

    cfg = Config().replace(features=dict(models=()))
    scene, _ = normalize_scene(load_scene(str(demo_scene_path()), DataConfig(format="colmap", holdout_every=8)))
    cfg = resolve_voxel_size(cfg, scene.points)
    state, _ = init_train_state(cfg, scene.points, len(scene.train_indices), scene.extent, make_strategies(cfg))
    anchors, nets, splat = state.anchors, state.nets, cfg.splat

    @jax.jit
    def decode(camera, index):
        g, _ = decode_view(nets, anchors, camera, index, cfg.model, anchors.capacity)
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, camera.world_to_camera, camera.K,
                                 camera.width, camera.height, antialiased=splat.antialiased, lens=camera.lens)
        grid = TileGrid(camera.width, camera.height, splat.tile_size)
        pairs = [jnp.sum(count_pairs(proj.means2d, proj.radii, proj.visible, grid, *extra))
                 for extra in ((), (proj.conics, proj.opacities))]
        return g, jnp.stack(pairs)

    per_view, views = [], []
    for position, index in enumerate(scene.train_indices):
        camera = Camera.of_scene(scene, int(index))
        g, pairs = decode(camera, jnp.int32(position))
        per_view.append([int(p) for p in pairs])
        if position < args.demo_views:
            active = np.asarray(g.active)
            params = tuple(jnp.asarray(np.asarray(x)[active])
                           for x in (g.means, g.quats, g.scales, g.opacities, g.colors))
            view = measure_view(params, camera.world_to_camera, camera.K, camera.width, camera.height,
                                tile_size=splat.tile_size, antialiased=splat.antialiased,
                                compositor=Compositor(args.backend, splat.chunk_size), repeats=args.repeats)
            views.append(dict(view=int(index), active_gaussians=int(active.sum()), **view))
    box, exact = np.asarray(per_view).T
    return dict(scene="demo", width=camera.width, height=camera.height, tile_size=splat.tile_size,
                antialiased=splat.antialiased, training_views=len(per_view),
                pairs_all_views=dict(box_mean=float(box.mean()), exact_mean=float(exact.mean()),
                                     ratio_mean=float(np.mean(exact / np.maximum(box, 1))),
                                     box_max=int(box.max()), exact_max=int(exact.max())),
                views=views)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["random", "demo"], choices=["random", "demo"])
    parser.add_argument("--gaussians", type=int, default=50_000, help="random scene")
    parser.add_argument("--size", type=int, default=256, help="random scene: image side")
    parser.add_argument("--tile-size", type=int, default=8, help="random scene (the demo uses splat.tile_size)")
    parser.add_argument("--elongation", type=float, default=0.0,
                        help="random scene: one axis of each Gaussian stretched by e^U(0, this) (0: as drawn)")
    parser.add_argument("--demo-views", type=int, default=2, help="demo views rendered and timed")
    parser.add_argument("--backend", default="auto", choices=["auto", "jax", "pallas"])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    cases = [random_case(args) if name == "random" else demo_case(args) for name in args.scenes]
    print(json.dumps(dict(device=jax.devices()[0].device_kind, platform=platform.platform(),
                          backend=splat_render.resolve_backend(args.backend), cases=cases), indent=1))


if __name__ == "__main__":
    main()
