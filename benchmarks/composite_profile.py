"""Where the compositor's time goes on one real view; prints JSON.

The initial model of a scene (anchors from its SfM points, as ``cusgs-train`` builds it) is
decoded, compacted, projected and binned at its first training view exactly as the training
step does; then, on those sorted inputs, times (median of ``--repeats`` after a compiling call):

- ``forward``: :func:`cusgs_jax.splat.composite.composite_tiles` alone;
- ``forward_backward``: its VJP with a random cotangent (forward with residuals, then the backward);
- ``backward``: the difference;

for each ``--lanes`` × ``--chunk`` setting asked (default: the library's own choice), and reports
the view's tile pairs, the busiest tile's pair count and the number of loop iterations
(chunks on the busiest lane schedule), so cost can be read per pair.

    python benchmarks/composite_profile.py --scene demo
    python benchmarks/composite_profile.py --scene ~/.cache/cusgs_jax/scale_bench/<scene> --chunk 8 16 32
"""

from __future__ import annotations

import argparse
import json


def sorted_inputs(scene_path: str, view: int, tile_size: int | None = None):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cusgs_jax.config import Config, DataConfig
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.densify.factory import make_strategies
    from cusgs_jax.model.active import compact_gaussians, select_active
    from cusgs_jax.model.decode import decode_view
    from cusgs_jax.splat.project import project_gaussians
    from cusgs_jax.splat.tiles import TileGrid, intersect_tiles
    from cusgs_jax.training import capacity
    from cusgs_jax.training.render import most_work
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.types import Camera

    if scene_path == "demo":
        from cusgs_jax.data.demo import demo_scene_path
        scene_path = str(demo_scene_path())
    cfg = Config().replace(features=dict(models=()))
    if tile_size:
        cfg = cfg.replace(splat=dict(tile_size=tile_size))
    scene, _ = normalize_scene(load_scene(scene_path, DataConfig(format="colmap", holdout_every=8)))
    cfg = resolve_voxel_size(cfg, scene.points)
    train_idx = scene.train_indices
    state, _ = init_train_state(cfg, scene.points, len(train_idx), scene.extent, make_strategies(cfg))
    camera = Camera.of_scene(scene, int(train_idx[view]))
    index = jnp.int32(view)
    caps = capacity.Capacities.fitted(most_work(state.anchors, state.nets, [(camera, index)], cfg),
                                      state.anchors.capacity, cfg.model.n_offsets)
    anchors, nets = state.anchors, state.trainable
    nets = {k: v for k, v in nets.items() if k != "anchor"}
    anchors = anchors.replace(params=state.trainable["anchor"])
    n = cfg.model.n_offsets
    grid = TileGrid(int(camera.width), int(camera.height), int(cfg.splat.tile_size))

    @jax.jit
    def prepare(anchors, nets, camera, index):
        g, _ = decode_view(nets, anchors, camera, index, cfg.model, caps.visible_slots(anchors.capacity))
        g = compact_gaussians(g, select_active(g.active, caps.active_gaussians(anchors.capacity, n)))
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, camera.world_to_camera, camera.K,
                                 camera.width, camera.height, antialiased=cfg.splat.antialiased)
        isect = intersect_tiles(proj.means2d, proj.radii, proj.depths, proj.visible, grid,
                                caps.pairs(anchors.capacity, n), proj.conics, proj.opacities)  # as rasterize bins
        depth = jnp.where(proj.visible, proj.depths, 0.0)
        features = jnp.concatenate([g.colors, depth[:, None]], axis=-1)
        o = isect.order
        return (proj.means2d[o], proj.conics[o], proj.opacities[o], features[o],
                isect.pair_gaussians, isect.tile_starts, isect.tile_ends)

    inputs = jax.block_until_ready(prepare(anchors, nets, camera, index))
    lengths = np.asarray(inputs[6] - inputs[5])
    info = dict(scene=scene_path, view=view, width=int(camera.width), height=int(camera.height),
                tiles=int(grid.num_tiles), tile_size=int(grid.tile_size), pairs=int(lengths.sum()), busiest_tile=int(lengths.max()),
                tiles_with_work=int((lengths > 0).sum()), gaussians=int(inputs[0].shape[0]),
                chunk_default=int(cfg.splat.chunk_size))
    return grid, inputs, info


def top_ops(fn, args, count: int = 25) -> dict:
    """Milliseconds per XLA op name (summed over all calls) of one ``fn(*args)``, costliest first."""
    import collections
    import glob
    import os
    import tempfile

    import jax

    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            jax.block_until_ready(fn(*args))
        path = glob.glob(os.path.join(folder, "**", "*.xplane.pb"), recursive=True)[0]
        data = jax.profiler.ProfileData.from_file(path)
    totals = collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            if "python" in line.name.lower():
                continue
            for event in line.events:
                totals[event.name] += event.duration_ns / 1e6
    return dict(totals.most_common(count))


def main(argv=None):
    import jax
    import numpy as np

    from timing import median_seconds

    from cusgs_jax.splat.composite import composite_tiles, default_lanes

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--view", type=int, default=0)
    parser.add_argument("--lanes", type=int, nargs="*", default=None, help="default: the library's choice")
    parser.add_argument("--chunk", type=int, nargs="*", default=None, help="default: the config's chunk size")
    parser.add_argument("--tile-size", type=int, default=None, help="default: the config's")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--trace", action="store_true",
                        help="also profile one fwd+bwd with jax.profiler and list the costliest XLA ops")
    args = parser.parse_args(argv)

    grid, inputs, info = sorted_inputs(args.scene, args.view, args.tile_size)
    rng = np.random.default_rng(0)
    rows = []
    for lanes in args.lanes or [default_lanes(grid.num_tiles)]:
        for chunk in args.chunk or [info["chunk_default"]]:
            fwd = jax.jit(lambda *a: composite_tiles(grid, chunk, lanes, *a))
            out = fwd(*inputs)
            ct_colors = rng.normal(size=out.colors.shape).astype(np.float32)
            ct_trans = rng.normal(size=out.transmittance.shape).astype(np.float32)

            def loss(means2d, conics, opacities, features, pairs, starts, ends):
                o = composite_tiles(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends)
                return (o.colors * ct_colors).sum() + (o.transmittance * ct_trans).sum()

            both = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))
            jax.block_until_ready((fwd(*inputs), both(*inputs)))  # compile both
            f = median_seconds(fwd, inputs, args.repeats)
            fb = median_seconds(both, inputs, args.repeats)
            row = dict(lanes=lanes, chunk=chunk, forward_ms=1e3 * f, forward_backward_ms=1e3 * fb,
                       backward_ms=1e3 * (fb - f), ns_per_pair_fwd_bwd=1e9 * fb / max(info["pairs"], 1))
            if args.trace:
                row["top_ops_ms"] = top_ops(both, inputs)
            rows.append(row)
    print(json.dumps(dict(**info, jax=jax.__version__, rows=rows), indent=1))


if __name__ == "__main__":
    main()
