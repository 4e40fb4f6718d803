"""How training scales with scene size on the demo room; writes JSON and a PNG.

Two axes of demo scenes (``cusgs_jax.data.demo.generate_demo_scene``, cameras
orbiting the table 360°), cached under ``--cache``:

* points: 160×120, 30 views, SfM points 10k, 25k, 50k, 100k, 200k (the
  generator keeps only points seen in ≥ 2 views, so it is asked for
  ``--oversample`` × more and the kept count is reported);
* pixels: ~25k points, 30 views, 160×120, 320×240, 640×480, 1280×960;
* ``--target`` adds one point: 60 views, 640×480, ~100k points.

A scene on both axes (160×120 with 25k points) is measured once. Every grid
point runs in a fresh subprocess (the script calls itself with
``--one SPEC``), so its peak RSS is its own. A point:

1. trains a short run through the app (``app.run.setup`` → ``start`` → ``train`` →
   ``finalise``, RGB only, ``--run-steps`` steps with the growing and pruning
   schedules compressed into the run so anchors grow and capacity changes are
   counted) and reads ``eval.json``'s ``alive_anchors``,
   ``recompilations`` (capacity growths) and ``render_ms_per_view`` (median
   held-out render of the compacted final model);
2. times a fresh ``make_train_step`` on the final state: compile time (first
   call minus the median steady call), median of ``--steps`` steps after
   ``--warmup`` steps, and XLA's memory estimate of the compiled step
   (``lower().compile().memory_analysis()``: arguments + outputs + temporaries);
3. breaks one step into stages, each its own jitted function on the same
   inputs (median of ``--stage-repeats`` calls after a compiling call):
   ``decode`` (``model.decode.decode_view``), ``project_sort``
   (``model.active`` compaction + ``splat.project.project_gaussians`` + ``splat.tiles.intersect_tiles``),
   ``composite_fwd`` (``splat.composite.composite_tiles``),
   ``loss_rest_fwd`` (forward loss minus those three: gathers, SSIM, …),
   ``backward`` (``value_and_grad`` of the step loss minus its forward) and
   ``update_rest`` (the whole step minus ``value_and_grad``: Adam, statistics);
   the six add up to the step time (``loss_rest_fwd`` and ``update_rest`` are
   differences, clipped at 0: separately jitted stages can sum to more than the
   fused forward; ``forward_s`` and ``value_and_grad_s`` keep the raw numbers);
4. reports process peak RSS (``VmHWM`` and ``ru_maxrss``) and the RSS after
   importing JAX (baseline).

The parent fits least-squares slopes of log(step time) and log(peak memory)
against log(alive anchors) on the points axis and against log(pixels) on the
pixels axis, names the dominant stage at each axis end, and writes
``<out-dir>/scale.json`` and ``scale.png`` (``scale_quick.*`` with ``--quick``).

Usage:
  python benchmarks/scale_bench.py                   # points and pixels axes
  python benchmarks/scale_bench.py --target          # ... plus the 60-view 640×480 ~100k point
  python benchmarks/scale_bench.py --quick           # two tiny points per axis (smoke test)
  python benchmarks/scale_bench.py --axes points --points 10000 50000 --steps 10
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

STAGES = ("decode", "project_sort", "composite_fwd", "loss_rest_fwd", "backward", "update_rest")
DEFAULT_POINTS = (10_000, 25_000, 50_000, 100_000, 200_000)
DEFAULT_SIZES = ("160x120", "320x240", "640x480", "1280x960")
REPO = pathlib.Path(__file__).resolve().parent.parent


# --- parent: scenes, grid, subprocesses, fits, plot -------------------------------------------


def scene_dir(cache: pathlib.Path, views: int, width: int, height: int, num_points: int, seed: int = 0):
    """The cached demo scene for these parameters, generated (atomically) on first use."""
    from cusgs_jax.data.demo import FORMAT_VERSION, generate_demo_scene

    final = cache / f"demo{FORMAT_VERSION}-s{seed}-v{views}-{width}x{height}-p{num_points}"
    if (final / "scene.json").is_file():
        return final
    cache.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=cache))
    try:
        start = time.perf_counter()
        generate_demo_scene(tmp, seed=seed, num_views=views, width=width, height=height, num_points=num_points,
                            overwrite=True)
        os.replace(tmp, final)
        print(f"generated {final.name} in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def build_grid(args) -> list[dict]:
    """Grid points as specs ``{axes, views, width, height, points_target}`` (duplicates merged)."""
    if args.quick:
        pts = dict(views=8, width=80, height=60)
        grid = [dict(axis="points", points_target=p, **pts) for p in (1000, 3000)]
        grid += [dict(axis="pixels", points_target=3000, views=8, width=w, height=h) for w, h in ((80, 60), (128, 96))]
        if "target" in args.axes:
            grid.append(dict(axis="target", points_target=4000, views=12, width=96, height=72))
    else:
        grid = []
        if "points" in args.axes:
            grid += [dict(axis="points", points_target=p, views=30, width=160, height=120) for p in args.points]
        if "pixels" in args.axes:
            for size in args.sizes:
                w, h = (int(v) for v in size.lower().split("x"))
                grid.append(dict(axis="pixels", points_target=args.pixel_points, views=30, width=w, height=h))
        if "target" in args.axes:
            grid.append(dict(axis="target", points_target=100_000, views=60, width=640, height=480))
    merged: dict[tuple, dict] = {}
    for g in grid:
        key = (g["views"], g["width"], g["height"], g["points_target"])
        merged.setdefault(key, dict(g, axes=[]))["axes"].append(g.pop("axis"))
    for spec in merged.values():
        spec.pop("axis", None)
    return list(merged.values())


def run_point(spec: dict, timeout: float) -> dict:
    """Measure one grid point in a fresh interpreter; returns its JSON (or an error record)."""
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--one", json.dumps(spec)],
                              stdout=subprocess.PIPE, stderr=None, text=True, timeout=timeout, cwd=REPO)
    except subprocess.TimeoutExpired:
        return dict(spec, error=f"timed out after {timeout:.0f} s", wall_s=time.perf_counter() - start)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        return dict(spec, error=f"child exited with {proc.returncode}", wall_s=time.perf_counter() - start)
    return dict(json.loads(lines[-1]), wall_s=time.perf_counter() - start)


def slope(xs, ys):
    """Least-squares slope of log y against log x (None with fewer than two usable points)."""
    pairs = [(x, y) for x, y in zip(xs, ys) if x and y and x > 0 and y > 0]
    if len({x for x, _ in pairs}) < 2:
        return None
    lx, ly = np.log([p[0] for p in pairs]), np.log([p[1] for p in pairs])
    return float(np.polyfit(lx, ly, 1)[0])


def dominant(row: dict) -> dict | None:
    stages = row.get("stages_s")
    if not stages:
        return None
    name = max(STAGES, key=lambda s: stages[s])
    total = sum(stages[s] for s in STAGES)
    return dict(stage=name, seconds=stages[name], fraction=stages[name] / total if total else None)


def summarise(rows: list[dict]) -> dict:
    """Fitted exponents and the dominant stage at both ends of each axis."""
    out = {}
    for axis, xkey in (("points", "anchors"), ("pixels", "pixels")):
        pts = sorted((r for r in rows if axis in r["axes"] and "error" not in r), key=lambda r: r[xkey])
        if not pts:
            continue
        xs = [r[xkey] for r in pts]
        out[axis] = dict(
            x=xkey, n=len(pts),
            exponent_step_time=slope(xs, [r["median_step_s"] for r in pts]),
            exponent_peak_rss=slope(xs, [r["peak_rss_bytes"] for r in pts]),
            exponent_peak_rss_above_baseline=slope(xs, [r["peak_rss_bytes"] - r["baseline_rss_bytes"] for r in pts]),
            exponent_rss_after_steps=slope(xs, [r.get("rss_after_steps_bytes") for r in pts]),
            exponent_xla_bytes=slope(xs, [r["xla_bytes"] for r in pts]),
            exponent_render_ms=slope(xs, [r["render_ms_per_view"] for r in pts]),
            smallest=dict({xkey: xs[0]}, dominant=dominant(pts[0])),
            largest=dict({xkey: xs[-1]}, dominant=dominant(pts[-1])),
        )
    return out


def plot(rows: list[dict], fits: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error" not in r]
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    for ax, axis, xkey, label in ((axes[0], "points", "anchors", "alive anchors"),
                                  (axes[1], "pixels", "pixels", "pixels per view")):
        pts = sorted((r for r in ok if axis in r["axes"]), key=lambda r: r[xkey])
        fit = fits.get(axis, {})
        if pts:
            xs = [r[xkey] for r in pts]
            ax.loglog(xs, [r["median_step_s"] for r in pts], "o-", color="C0",
                      label=f"step time (slope {_fmt(fit.get('exponent_step_time'))})")
            comp = [(x, r["stages_s"]["composite_fwd"] + r["stages_s"]["backward"])
                    for x, r in zip(xs, pts) if r.get("stages_s")]
            if comp:
                ax.loglog(*zip(*comp), "^--", color="C2", alpha=0.7, label="composite fwd + backward")
            ax.set_ylabel("seconds")
            ax2 = ax.twinx()
            ax2.set_yscale("log")
            ax2.plot(xs, [r["peak_rss_bytes"] / 2**20 for r in pts], "s-", color="C3",
                     label=f"peak RSS (slope {_fmt(fit.get('exponent_peak_rss'))})")
            xla = [(x, r["xla_bytes"] / 2**20) for x, r in zip(xs, pts) if r.get("xla_bytes")]
            if xla:
                ax2.plot(*zip(*xla), "d--", color="C1",
                         label=f"XLA step estimate (slope {_fmt(fit.get('exponent_xla_bytes'))})")
            ax2.set_ylabel("MiB")
            handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
            ax.legend(handles, [h.get_label() for h in handles], fontsize=7, loc="upper left")
        ax.set_xlabel(label + " (log)")
        ax.set_title(f"{axis} axis")
        ax.grid(True, which="both", alpha=0.3)
    ax = axes[2]
    bars = sorted((r for r in ok if r.get("stages_s")),
                  key=lambda r: (min(_AXIS_ORDER.get(a, 9) for a in r["axes"]), r["anchors"], r["pixels"]))
    # shares of each step (linear 0-100 %), the step time written above each bar
    totals = np.array([max(r["stage_sum_s"], 1e-12) for r in bars])
    bottom = np.zeros(len(bars))
    for i, stage in enumerate(STAGES):
        share = 100.0 * np.array([r["stages_s"][stage] for r in bars]) / totals
        ax.bar(range(len(bars)), share, bottom=bottom, label=stage, color=f"C{i}")
        bottom += share
    for x, r in enumerate(bars):
        ax.text(x, 101, f"{r['median_step_s']:.2g} s", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(bars)))
    ax.set_xticklabels([f"{r['anchors'] / 1000:.1f}k a\n{r['width']}x{r['height']}\n{r['views']}v" for r in bars],
                       fontsize=7)
    ax.set_ylim(0, 112)
    ax.set_ylabel("share of one step (%)")
    ax.set_title("one step by stage (step time above each bar)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


_AXIS_ORDER = {"points": 0, "pixels": 1, "target": 2}


def _fmt(x):
    return "n/a" if x is None else f"{x:.2f}"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--axes", nargs="+", choices=("points", "pixels", "target"), default=["points", "pixels"])
    parser.add_argument("--target", action="store_true", help="add the 60-view 640×480 ~100k-point scene")
    parser.add_argument("--points", type=int, nargs="+", default=list(DEFAULT_POINTS),
                        help="kept SfM points wanted on the points axis (160×120, 30 views)")
    parser.add_argument("--sizes", nargs="+", default=list(DEFAULT_SIZES), help="WxH on the pixels axis")
    parser.add_argument("--pixel-points", type=int, default=25_000, help="SfM points on the pixels axis")
    parser.add_argument("--oversample", type=float, default=1.03,
                        help="ask the generator for this many times the wanted points (some are dropped)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps (median)")
    parser.add_argument("--warmup", type=int, default=2, help="steps after the compiling call, not timed")
    parser.add_argument("--run-steps", type=int, default=100,
                        help="short training run before timing (growing/pruning compressed into it)")
    parser.add_argument("--stage-repeats", type=int, default=5)
    parser.add_argument("--voxel-size", type=float, default=None,
                        help="model.voxel_size (units of the scene extent); default: the config's (auto)")
    parser.add_argument("--quick", action="store_true", help="two tiny points per axis, few steps (smoke test)")
    parser.add_argument("--cache", type=pathlib.Path,
                        default=pathlib.Path.home() / ".cache" / "cusgs_jax" / "scale_bench")
    parser.add_argument("--out-dir", type=pathlib.Path, default=REPO / "benchmarks" / "results" / "scale")
    parser.add_argument("--out", type=pathlib.Path, default=None, help="JSON path (default <out-dir>/scale.json)")
    parser.add_argument("--point-timeout", type=float, default=7200.0, help="seconds per grid point")
    parser.add_argument("--one", metavar="SPEC", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(measure_point(json.loads(args.one))), flush=True)
        return
    if args.target and "target" not in args.axes:
        args.axes.append("target")
    if args.quick:
        args.steps, args.warmup, args.run_steps, args.stage_repeats = 3, 1, 12, 2

    start = time.perf_counter()
    grid = build_grid(args)
    rows = []
    for spec in grid:
        num_points = int(math.ceil(spec["points_target"] * args.oversample))
        spec = dict(spec, num_points_sampled=num_points, steps=args.steps, warmup=args.warmup,
                    run_steps=args.run_steps, stage_repeats=args.stage_repeats, voxel_size=args.voxel_size)
        try:
            spec["scene"] = str(scene_dir(args.cache, spec["views"], spec["width"], spec["height"], num_points))
        except Exception as exc:  # noqa: BLE001 - record it and go on with the other points
            rows.append(dict(spec, error=f"scene generation failed: {type(exc).__name__}: {exc}"))
            continue
        row = run_point(spec, args.point_timeout)
        rows.append(row)
        brief = {k: row.get(k) for k in ("axes", "views", "width", "height", "kept_points", "anchors",
                                         "median_step_s", "compile_s", "peak_rss_bytes", "error", "wall_s")}
        print(json.dumps(brief), file=sys.stderr, flush=True)
    fits = summarise(rows)
    stem = "scale_quick" if args.quick else "scale"
    args.out_dir.mkdir(parents=True, exist_ok=True)
    png = args.out_dir / f"{stem}.png"
    if any("error" not in r for r in rows):
        plot(rows, fits, png)
    report = dict(benchmark="scale", quick=args.quick, platform=_platform(), settings=dict(
        steps=args.steps, warmup=args.warmup, run_steps=args.run_steps, stage_repeats=args.stage_repeats,
        voxel_size=args.voxel_size, oversample=args.oversample), stages=list(STAGES),
        fits=fits, results=rows, plot=str(png), total_wall_s=time.perf_counter() - start)
    text = json.dumps(report, indent=1)
    (args.out or args.out_dir / f"{stem}.json").write_text(text + "\n")
    print(text)


def _platform() -> dict:
    import importlib.metadata as md

    return dict(jax=md.version("jax"), cpu_count=os.cpu_count(), machine=platform.machine(),
                python=platform.python_version())


# --- child: one grid point --------------------------------------------------------------------


def _rss() -> dict:
    """Current and peak resident set of this process in bytes (/proc VmRSS, VmHWM; ru_maxrss)."""
    status = {}
    try:
        for line in pathlib.Path("/proc/self/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                status[key] = int(value.split()[0]) * 1024
    except OSError:
        pass
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    return dict(rss=status.get("VmRSS"), hwm=status.get("VmHWM", maxrss), maxrss=maxrss)


def short_run(spec: dict, workdir: str):
    """The glue to the app (kept in one place): a short real run, then a fresh step on its final state.

    Returns ``((session, loop), eval_result, info, step_fn, batches)``; the step is built with the
    loop's grown capacities (``loop.capacities``).
    """
    from cusgs_jax.app import run as app_run
    from cusgs_jax.config import Config
    from cusgs_jax.training import step as train_step

    n = int(spec["run_steps"])
    every = max(2, n // 6)  # two or more grow/prune passes inside the run
    cfg = Config().replace(
        data=dict(path=spec["scene"]),
        train=dict(iterations=n, progress=False, checkpoint_every=0, log_every=max(1, min(10, n))),
        eval=dict(every=0, save_renders=False), features=dict(models=()),
        **({"model": dict(voxel_size=float(spec["voxel_size"]))} if spec.get("voxel_size") else {}),
        grow=dict(stats_start=0, start=2 * every, interval=every, stop=n),
        prune=dict(start=3 * every, interval=every, stop=n))
    session = app_run.setup(cfg, workdir)
    loop = app_run.start(session)
    info = dict(initial_anchors=int(np.sum(loop.state.anchors.alive)),
                initial_capacity=int(loop.state.anchors.capacity), kept_points=int(len(session.scene.points)),
                train_views=int(len(session.train_idx)), held_out_views=int(len(session.test_idx)))
    app_run.train(session, loop)
    result = app_run.finalise(session, loop).to_json()
    step_fn = train_step.make_train_step(session.cfg, loop.tx, session.strategies, loop.capacities)
    return (session, loop), result, info, step_fn, session.batches


def _timed(fn, *args, repeats: int):
    """(first call seconds, median of ``repeats`` later calls, last output)."""
    import jax

    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return first, float(np.median(times)), out


def stage_breakdown(cfg, capacities, state, batch, repeats: int) -> tuple[dict, dict]:
    """Seconds of each stage of one step (``STAGES`` minus ``update_rest``) and their compile seconds.

    The stages follow the step (``training.step._view_pass``): ``decode`` gathers the visible
    slots and decodes them, ``project_sort`` compacts the active Gaussians and projects, sorts
    and bins them with the step's pair capacity, ``composite_fwd`` composites the tiles.
    """
    import jax
    import jax.numpy as jnp

    from cusgs_jax import losses
    from cusgs_jax.model.active import compact_gaussians, select_active
    from cusgs_jax.model.decode import decode_view
    from cusgs_jax.splat.composite import composite_tiles, default_lanes
    from cusgs_jax.splat.project import project_gaussians
    from cusgs_jax.splat.tiles import TileGrid, intersect_tiles
    from cusgs_jax.training.render import render_model
    from cusgs_jax.training.step import _view_pass

    camera, index = batch["camera"], batch["index"]
    trainable, anchors = state.trainable, state.anchors
    splat, n = cfg.splat, cfg.model.n_offsets
    grid = TileGrid(int(camera.width), int(camera.height), int(splat.tile_size))
    num_slots = capacities.visible_slots(anchors.capacity)
    active_capacity = capacities.active_gaussians(anchors.capacity, n)
    pair_capacity = capacities.pairs(anchors.capacity, n)

    decode = jax.jit(lambda nets, anchors, camera, index: decode_view(nets, anchors, camera, index, cfg.model,
                                                                      num_slots)[0])

    def project_sort(g, camera):  # as training.render.render_gaussians → splat.render.rasterize
        g = compact_gaussians(g, select_active(g.active, active_capacity))
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, camera.world_to_camera.astype(g.means.dtype),
                                 camera.K.astype(g.means.dtype), camera.width, camera.height,
                                 antialiased=splat.antialiased)
        isect = intersect_tiles(proj.means2d, proj.radii, proj.depths, proj.visible, grid, pair_capacity,
                                proj.conics, proj.opacities)  # the exact ellipse-tile pairs, as rasterize bins
        depth = jnp.where(proj.visible, proj.depths, 0.0)
        features = jnp.concatenate([g.colors, depth[:, None]], axis=-1)
        order = isect.order
        return (proj.means2d[order], proj.conics[order], proj.opacities[order], features[order],
                isect.pair_gaussians, isect.tile_starts, isect.tile_ends)

    lanes = default_lanes(grid.num_tiles)
    composite = jax.jit(lambda *a: composite_tiles(grid, int(splat.chunk_size), lanes, *a))

    def forward_loss(trainable, anchors, batch):
        nets = {k: v for k, v in trainable.items() if k != "anchor"}
        out, _, _ = render_model(anchors.replace(params=trainable["anchor"]), nets, batch["camera"],
                                 batch["index"], cfg, capacities)
        return losses.image_loss(out.image[..., :3], batch["image"], jnp.zeros((1, 3)), jnp.zeros(1, bool),
                                 l1_weight=cfg.loss.l1_weight, ssim_weight=cfg.loss.ssim_weight,
                                 volume_weight=0.0)[0]

    one = _view_pass(cfg, capacities, anchors.capacity)
    key = jax.random.PRNGKey(0)
    forward = jax.jit(forward_loss)
    both = jax.jit(lambda trainable, anchors, batch, key: one(trainable, anchors, batch, key, None)[:2])  # no loss terms: no state

    seconds, compile_s = {}, {}
    first, seconds["decode"], gaussians = _timed(decode, trainable, anchors, camera, index, repeats=repeats)
    compile_s["decode"] = first - seconds["decode"]
    first, seconds["project_sort"], sorted_inputs = _timed(jax.jit(project_sort), gaussians, camera, repeats=repeats)
    compile_s["project_sort"] = first - seconds["project_sort"]
    first, seconds["composite_fwd"], _ = _timed(composite, *sorted_inputs, repeats=repeats)
    compile_s["composite_fwd"] = first - seconds["composite_fwd"]
    first, fwd, _ = _timed(forward, trainable, anchors, batch, repeats=repeats)
    compile_s["forward"] = first - fwd
    first, fwd_bwd, _ = _timed(both, trainable, anchors, batch, key, repeats=repeats)
    compile_s["value_and_grad"] = first - fwd_bwd
    seconds["loss_rest_fwd"] = max(0.0, fwd - seconds["decode"] - seconds["project_sort"] - seconds["composite_fwd"])
    seconds["backward"] = max(0.0, fwd_bwd - fwd)
    extra = dict(forward_s=fwd, value_and_grad_s=fwd_bwd, gaussians=int(gaussians.means.shape[0]),
                 active_gaussians=int(jnp.sum(gaussians.active)), active_capacity=active_capacity,
                 pair_capacity=pair_capacity, tile_pairs=int(sorted_inputs[6][-1]))
    return seconds, dict(stage_compile_s=compile_s, **extra)


def measure_point(spec: dict) -> dict:
    import jax
    import jax.numpy as jnp

    jax.block_until_ready(jnp.zeros(8) + 1)
    baseline = _rss()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="scale_bench_") as workdir:
        (session, loop), result, info, step_fn, batches = short_run(spec, workdir)
    run_s = time.perf_counter() - start
    after_run = _rss()

    state = loop.state
    loop.state = None  # the step donates it
    start = time.perf_counter()
    state, metrics = step_fn(state, batches(0))
    jax.block_until_ready(metrics)
    first = time.perf_counter() - start
    for i in range(spec["warmup"]):
        state, metrics = step_fn(state, batches(1 + i))
        jax.block_until_ready(metrics)
    times, dropped = [], 0
    for i in range(spec["steps"]):
        batch = batches(1 + spec["warmup"] + i)
        start = time.perf_counter()
        state, metrics = step_fn(state, batch)
        jax.block_until_ready(metrics)
        times.append(time.perf_counter() - start)
        dropped += sum(int(metrics.get(k, 0)) for k in _DROPPED)
    step_s = float(np.median(times))
    after_steps = _rss()

    start = time.perf_counter()
    mem = step_fn.lower(state, batches(0)).compile().memory_analysis()
    aot_s = time.perf_counter() - start
    xla = None
    if mem is not None:
        xla = dict(argument=int(mem.argument_size_in_bytes), output=int(mem.output_size_in_bytes),
                   temp=int(mem.temp_size_in_bytes), alias=int(getattr(mem, "alias_size_in_bytes", 0)))

    start = time.perf_counter()
    try:
        stages, stage_info = stage_breakdown(session.cfg, loop.capacities, state, batches(0),
                                             int(spec["stage_repeats"]))
        stages["update_rest"] = max(0.0, step_s - stage_info["value_and_grad_s"])
    except Exception as exc:  # keep the step numbers of this point
        import traceback

        traceback.print_exc()
        stages, stage_info = None, dict(stages_error=f"{type(exc).__name__}: {exc}")
    stages_wall_s = time.perf_counter() - start
    final = _rss()

    anchors = int(np.sum(state.anchors.alive))
    width, height = int(session.scene.width), int(session.scene.height)
    return dict(
        {k: spec[k] for k in ("axes", "views", "width", "height", "points_target", "num_points_sampled", "scene")},
        pixels=width * height, **info, anchors=anchors, alive_anchors_end=int(result["alive_anchors"]),
        capacity=int(state.anchors.capacity), recompilations=int(result["recompilations"]),
        run_steps=int(spec["run_steps"]), run_wall_s=run_s, train_wall_s=float(result["train_wall_s"]),
        psnr=float(result["psnr"]), render_ms_per_view=result["render_ms_per_view"],
        compile_s=max(0.0, first - step_s), first_step_s=first, median_step_s=step_s,
        step_times_s=[round(t, 5) for t in times], aot_compile_s=aot_s,
        xla=xla, xla_bytes=(xla["argument"] + xla["output"] + xla["temp"]) if xla else None,
        peak_rss_bytes=final["hwm"], ru_maxrss_bytes=final["maxrss"], baseline_rss_bytes=baseline["rss"],
        peak_rss_after_run_bytes=after_run["hwm"], peak_rss_after_steps_bytes=after_steps["hwm"],
        rss_after_steps_bytes=after_steps["rss"],
        stages_s=stages, stage_sum_s=sum(stages[s] for s in STAGES) if stages else None,
        stages_wall_s=stages_wall_s, **stage_info,
        voxel_size=float(session.cfg.model.voxel_size), replayed_steps=result.get("replayed_steps"),
        capacities=loop.capacities.as_dict(), dropped_in_timed_steps=dropped)


# names of the step metrics that count work a step dropped (old and new spellings)
_DROPPED = ("dropped_anchors", "dropped_gaussians", "dropped_pairs")


if __name__ == "__main__":
    main()
