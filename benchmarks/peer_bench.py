"""Our rasteriser against splax (chungmin99/splax), the fastest pure-JAX peer; prints JSON.

Same random Gaussians (``scenes.random_scene``, as ``splat_bench.py``), same camera, one
process. For every (G, resolution) cell and every renderer: compile time, XLA's peak-memory
estimate, forward median and forward+backward median (gradient of ``sum(image · w)``, ``w``
fixed random weights, with respect to means, quats, scales, opacities and colours). The
renderers are timed ALTERNATELY — round r calls each once, in rotating order — so load from
other work on the machine hits all of them alike; the medians are over rounds.

splax runs its pure-JAX path (``rasterize(..., mode="jax")``) driven as its own example does
(``Gaussian3D.from_props`` + ``Camera.from_K_and_viewmat`` → ``Camera.project`` →
``rasterize``), imported from a source folder (``--splax-src``; it needs ``jaxlie`` and
``jax_dataclasses``), from a copy with one bug fixed (:data:`SPLAX_PATCHES`: its 3D covariance
used the scales of Gaussians 0–2 for every Gaussian; ``--no-splax-patch`` runs it as is).
It keeps only the first ``max_intersects`` Gaussians (depth order) of a tile, so it runs in
two ways:

- ``splax_default``: its defaults, tile 40 and ``max_intersects`` 100 (drops Gaussians);
- ``splax_exact_t<N>``: tile N with ``max_intersects`` = the largest number of Gaussians any
  tile has, measured on the scene with splax's own bounding-box test, so nothing is dropped.
  Variants whose compiled program XLA sizes above ``--max-bytes`` are compiled, reported and
  not run.

The headline ratio is splax's fastest exact variant over ours (forward+backward). Picture
checks: PSNR of each splax image against ours rendered with splax's conventions as far as they
can be matched (``eps2d`` 0: splax has no 0.3 low-pass), and, for cells with at most
``--oracle-max-gaussians`` Gaussians, against the float64 oracle
(``cusgs_jax.testing.splat_reference``). The conventions that still differ are listed in the
JSON (``conventions``).

    git clone https://github.com/chungmin99/splax && pip install jaxlie jax_dataclasses
    python benchmarks/peer_bench.py --splax-src splax/src --quick
    python benchmarks/peer_bench.py --splax-src splax/src --splax-tiles 8 16 --gaussians 10000 50000 100000 --sizes 128 256
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import math
import os
import pathlib
import platform
import shutil
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from scenes import random_scene  # noqa: E402
from timing import median_seconds  # noqa: E402

from cusgs_jax.errors import UserError  # noqa: E402
from cusgs_jax.splat import Compositor, rasterize  # noqa: E402
from cusgs_jax.testing.splat_reference import rasterize_reference  # noqa: E402

KEYS = ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")
RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "peers"
SPLAX_DEFAULT_TILE = 40  # splax.rasterize's defaults
SPLAX_DEFAULT_MAX_INTERSECTS = 100

CONVENTIONS = [
    "low-pass: ours adds eps2d = 0.3 px^2 to the 2D covariance (gsplat); splax clamps the 2D "
    "covariance's eigenvalues at >= 0.1 (+1e-6) and adds nothing. Picture checks render ours "
    "with eps2d = 0; the timed 'ours' keeps the default 0.3 (larger footprints: more work for us)",
    "alpha: ours min(0.999, o e^-s), skipped below 1/255, pixel stops before T <= 1e-4; splax "
    "o e^-s unclamped, no threshold, no early stop (every listed Gaussian is composited)",
    "footprint: ours the box ceil(min(3.33, sqrt(2 ln(255 o))) sqrt(diag S')) around the mean; "
    "splax the box 3 max_i |R_ji s_i| (smaller than the 3-sigma box for rotated Gaussians), "
    "tested against the tile with both ends inclusive",
    "dropping: splax composites only the first max_intersects Gaussians (depth order) of each "
    "tile; ours keeps every pair (overflow 0 here)",
    "culling: splax culls only depth <= 0 (its near/far enter only an unused row of its "
    "projection matrix); ours culls z < 0.01 and off-screen footprints. The EWA Jacobian of "
    "splax has no frustum clamp (ours clamps x/z, y/z to 1.3x the frustum) and adds 1e-6 to z",
    "parameters: splax round-trips opacity and colour through clip(1e-6, 1-1e-6) + logit + "
    "sigmoid, scale through clip(>=1e-6) + log + exp, and clips the image to [0, 1]; its "
    "quaternions must be unit (jaxlie), so the splax wrapper normalises them (inside the "
    "differentiated function, like ours)",
    "pixel centres: ours samples pixel (i, j) at (j + 0.5, i + 0.5) with the mean at "
    "K (x/z, y/z, 1); splax samples (j, i) with the mean shifted by +0.5, i.e. (j - 0.5, i - 0.5) "
    "in our coordinates: its image is ours moved by one pixel. Picture checks render ours (and "
    "the oracle) with the principal point moved by +1 px so the samples coincide",
]


# --- splax ---------------------------------------------------------------------------------------


# (file, text, replacement): splax's Camera.project builds every Gaussian's 3D covariance with
# jnp.diag(scale**2) of the [G, 3] scales, i.e. the diagonal of that matrix (the scales of
# Gaussians 0, 1, 2) for all G; the batched diagonal is scale**2 itself. Same cost, and without
# it splax would not draw the scene's Gaussians (its example sets one scale for all, hiding it).
SPLAX_PATCHES = [("_camera.py", "jnp.diag(gaussians.scale**2),", "gaussians.scale**2,  # patched: batched diagonal")]


def patched_copy(package: pathlib.Path, patches, folder: pathlib.Path):
    """Copy ``package`` into ``folder`` and apply ``patches`` [(file, text, replacement)] there.

    Returns:
      (the copy's package folder, [{"file", "replaced", "by"}] applied).
    Raises:
      UserError: a text does not occur exactly once in its file.
    """
    copy = folder / package.name
    shutil.copytree(package, copy)
    applied = []
    for name, text, replacement in patches:
        source = (copy / name).read_text(encoding="utf-8")
        if source.count(text) != 1:
            raise UserError(f"--splax-src: {package.name}/{name} does not contain {text!r} exactly once "
                            "(another splax revision?); pass --no-splax-patch to run it unpatched")
        (copy / name).write_text(source.replace(text, replacement), encoding="utf-8")
        applied.append(dict(file=name, replaced=text, by=replacement))
    return copy, applied


def load_splax(src: str, patch: bool = True):
    """Import splax from its source folder (the one holding ``splax/``), from a patched copy
    (:data:`SPLAX_PATCHES`) unless ``patch`` is False.

    Returns:
      (splax module, jaxlie module, {file: sha256} of splax's original sources, patches applied).
    Raises:
      UserError: the folder has no splax package, a patch does not apply, or jaxlie /
        jax_dataclasses are missing.
    """
    package = pathlib.Path(src).expanduser().resolve() / "splax"
    if not (package / "__init__.py").is_file():
        raise UserError(f"--splax-src {src}: no splax/__init__.py there; extract chungmin99/splax "
                        "and pass its src folder (the one that holds splax/)")
    try:
        import jax_dataclasses  # noqa: F401  (splax's dependency, checked here for a clear message)
        import jaxlie
    except ImportError as exc:
        raise UserError(f"splax needs jaxlie and jax_dataclasses ({exc}); "
                        "install them with: pip install jaxlie jax_dataclasses") from exc
    digests = {p.name: hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in sorted(package.glob("*.py"))}
    applied = []
    if patch:
        package, applied = patched_copy(package, SPLAX_PATCHES, pathlib.Path(tempfile.mkdtemp(prefix="splax_")))
    sys.path.insert(0, str(package.parent))
    import splax

    if pathlib.Path(splax.__file__).resolve().parent != package:
        raise UserError(f"--splax-src {src}: another splax was imported ({splax.__file__}); "
                        "uninstall it or pass the folder it came from")
    return splax, jaxlie, digests, applied


def splax_project(splax, jaxlie, width: int, height: int):
    """``project(means, quats, scales, opacities, colors, viewmat, K) -> (Gaussian2D, depth [G])``,
    as splax's examples/train_scene.py: Gaussian3D.from_props + Camera.from_K_and_viewmat
    (whose pose is camera→world, hence the inverse of our world→camera viewmat)."""

    def project(means, quats, scales, opacities, colors, viewmat, K):
        unit = quats / jnp.linalg.norm(quats, axis=-1, keepdims=True)
        gaussians = splax.Gaussian3D.from_props(means, jaxlie.SO3(wxyz=unit), scales, colors, opacities)
        camera = splax.Camera.from_K_and_viewmat(K, jnp.linalg.inv(viewmat), width, height)
        return camera.project(gaussians)

    return project


def splax_renderer(splax, jaxlie, width: int, height: int, tile_size: int, max_intersects: int):
    """``render(*arrays) -> [H, W, 3]`` image of splax's pure-JAX rasteriser."""
    project = splax_project(splax, jaxlie, width, height)

    def render(*arrays):
        g2d, depth = project(*arrays)
        return splax.rasterize(g2d, depth, height, width, tile_size=tile_size,
                               max_intersects=max_intersects, mode="jax")

    return render


def splax_tiles(width: int, height: int, tile_size: int) -> jax.Array:
    """[T, 4] ``(x0, y0, x1, y1)`` of splax's tiles, in its order (splax._rasterizer.rasterize)."""
    across, down = math.ceil(width / tile_size), math.ceil(height / tile_size)
    corner = jnp.stack(jnp.meshgrid(jnp.arange(across), jnp.arange(down)), axis=-1).reshape(-1, 2)
    return jnp.concatenate([corner * tile_size, (corner + 1) * tile_size], axis=-1)


def splax_tile_counts(splax, jaxlie, width: int, height: int, tile_size: int):
    """``counts(*arrays) -> [T] int32``: Gaussians splax lists for each tile with no cap (the
    test of splax._select_hit_gs._get_intersections_from_depth, counted instead of truncated)."""
    project = splax_project(splax, jaxlie, width, height)
    tiles = splax_tiles(width, height, tile_size)

    def counts(*arrays):
        g2d, depth = project(*arrays)
        bbox = g2d.get_bbox()

        def one(tile):
            hit = ((bbox[:, 2] >= tile[0]) & (bbox[:, 0] <= tile[2])
                   & (bbox[:, 3] >= tile[1]) & (bbox[:, 1] <= tile[3]) & (depth > 0))
            return jnp.sum(hit, dtype=jnp.int32)

        return jax.lax.map(one, tiles)

    return jax.jit(counts)


# --- ours ------------------------------------------------------------------------------------


def our_renderer(width: int, height: int, tile_size: int, chunk_size: int, max_pairs: int, eps2d: float = 0.3):
    """``render(*arrays) -> [H, W, 3]`` image of ``cusgs_jax.splat.rasterize``."""

    def render(*arrays):
        return rasterize(*arrays, width, height, tile_size=tile_size, max_pairs=max_pairs, eps2d=eps2d,
                         compositor=Compositor(chunk_size=chunk_size)).image

    return render


def our_max_pairs(arrays, width: int, height: int, tile_size: int) -> int:
    """Pair capacity sized to the scene as splat_bench.py does: 1.25x the pairs of a generous probe."""
    num = arrays[0].shape[0]
    probe = rasterize(*arrays, width, height, tile_size=tile_size, max_pairs=40 * num)
    return int(1.25 * int(probe.num_pairs)) + 1024


# --- measuring -------------------------------------------------------------------------------


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of two [H, W, C] images on a peak of 1 (inf when equal)."""
    mse = float(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def _peak_bytes(compiled) -> int | None:
    mem = compiled.memory_analysis()
    if mem is None:
        return None
    return int(mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes)


def compile_renderer(render, arrays, weights):
    """Compile ``render`` and the gradient of ``sum(render(*arrays) · weights)`` w.r.t. the first five arrays.

    Returns:
      {"forward": compiled, "forward_backward": compiled} and a row of compile seconds and
      XLA peak-byte estimates.
    """
    def loss(*a):
        return jnp.sum(render(*a) * weights)

    programs, row = {}, {}
    for name, fn in (("forward", render), ("forward_backward", jax.grad(loss, argnums=(0, 1, 2, 3, 4)))):
        start = time.perf_counter()
        programs[name] = jax.jit(fn).lower(*arrays).compile()
        row[f"{name}_compile_s"] = time.perf_counter() - start
        row[f"{name}_peak_bytes"] = _peak_bytes(programs[name])
    return programs, row


def time_alternately(programs: dict, arrays, rounds: int) -> dict:
    """Median seconds of each compiled program, called once per round in rotating order
    (each warmed up once first) so that machine load affects all alike.

    Args:
      programs: {name: compiled callable}.
    Returns:
      {name: median seconds}.
    """
    names = list(programs)
    for name in names:
        jax.block_until_ready(programs[name](*arrays))
    times = {name: [] for name in names}
    for r in range(rounds):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            times[name].append(median_seconds(programs[name], arrays, 1))
    return {name: float(np.median(t)) for name, t in times.items()}


def measure_cell(splax_mods, num: int, size: int, args) -> dict:
    """Everything for one (G, size) cell; returns {"rows": [...], "pictures": {...}, ...}."""
    splax, jaxlie = splax_mods
    scene = random_scene(num, size, size)
    arrays = [jnp.asarray(scene[k]) for k in KEYS]
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(size, size, 3)).astype(np.float32))

    variants = {}  # name -> (render, description row)
    for tile in args.our_tiles:
        max_pairs = our_max_pairs(arrays, size, size, tile)
        variants[f"ours_t{tile}"] = (
            our_renderer(size, size, tile, args.chunk_size, max_pairs),
            dict(renderer="cusgs_jax", tile_size=tile, chunk_size=args.chunk_size, max_pairs=max_pairs, eps2d=0.3))
    counts = {tile: np.asarray(splax_tile_counts(splax, jaxlie, size, size, tile)(*arrays))
              for tile in sorted(set(args.splax_tiles) | {SPLAX_DEFAULT_TILE})}
    per_tile = {tile: dict(max=int(c.max()), mean=float(c.mean()), tiles=int(c.size), total=int(c.sum()))
                for tile, c in counts.items()}
    default_counts = counts[SPLAX_DEFAULT_TILE]
    variants["splax_default"] = (
        splax_renderer(splax, jaxlie, size, size, SPLAX_DEFAULT_TILE, SPLAX_DEFAULT_MAX_INTERSECTS),
        dict(renderer="splax", tile_size=SPLAX_DEFAULT_TILE, max_intersects=SPLAX_DEFAULT_MAX_INTERSECTS,
             dropped_listings=int(np.maximum(default_counts - SPLAX_DEFAULT_MAX_INTERSECTS, 0).sum()),
             tiles_dropping=int((default_counts > SPLAX_DEFAULT_MAX_INTERSECTS).sum())))
    for tile in args.splax_tiles:
        needed = max(1, per_tile[tile]["max"])
        variants[f"splax_exact_t{tile}"] = (
            splax_renderer(splax, jaxlie, size, size, tile, needed),
            dict(renderer="splax", tile_size=tile, max_intersects=needed, dropped_listings=0, tiles_dropping=0))

    programs, rows = {}, {}
    for name, (render, row) in variants.items():
        compiled, compile_row = compile_renderer(render, arrays, weights)
        row = dict(variant=name, gaussians=num, width=size, height=size, **row, **compile_row)
        programs[name] = {}
        for stage, program in compiled.items():
            peak = compile_row[f"{stage}_peak_bytes"] or 0
            if peak > args.max_bytes:
                row[f"{stage}_skipped"] = (f"XLA peak estimate {peak / 1e9:.2f} GB > --max-bytes "
                                           f"{args.max_bytes / 1e9:.2f} GB")
            else:
                programs[name][stage] = program
        rows[name] = row
        print(json.dumps(row), file=sys.stderr, flush=True)

    for stage in ("forward", "forward_backward"):
        medians = time_alternately({n: p[stage] for n, p in programs.items() if stage in p}, arrays, args.repeats)
        for name, seconds in medians.items():
            rows[name][f"{stage}_median_s"] = seconds

    images = {name: np.asarray(p["forward"](*arrays)) for name, p in programs.items() if "forward" in p}
    pictures = _picture_checks(images, arrays, size, args, variants)
    summary = _summary(rows)
    return dict(gaussians=num, width=size, height=size, splax_tile_counts=per_tile,
                rows=list(rows.values()), pictures=pictures, **summary)


def splax_pixel_grid(K: jax.Array) -> jax.Array:
    """[3, 3] intrinsics whose pixel samples are splax's: principal point moved by +1 px."""
    return K.at[0, 2].add(1.0).at[1, 2].add(1.0)


def _picture_checks(images: dict, arrays, size: int, args, variants) -> dict:
    """PSNR (dB) between the images. ``matched``: ours with splax's samples
    (:func:`splax_pixel_grid`) and eps2d 0 (splax has no low-pass); ``oracle``: the float64
    reference, with our samples and eps2d 0.3 for ours, splax's samples and eps2d 0 for splax."""
    ours_name = next(n for n in images if n.startswith("ours"))
    ours_row = variants[ours_name][1]
    shifted = [*arrays[:6], splax_pixel_grid(arrays[6])]
    matched = np.asarray(jax.jit(our_renderer(size, size, ours_row["tile_size"], args.chunk_size,
                                              ours_row["max_pairs"], eps2d=0.0))(*shifted))
    splax_images = {name: img for name, img in images.items() if name.startswith("splax")}
    checks = {f"{name}_vs_ours_matched": psnr(img, matched) for name, img in splax_images.items()}
    if arrays[0].shape[0] <= args.oracle_max_gaussians:
        oracle = rasterize_reference(*[np.asarray(a) for a in arrays], size, size, eps2d=0.3)["image"]
        checks[f"{ours_name}_vs_oracle"] = psnr(images[ours_name], oracle)
        oracle = rasterize_reference(*[np.asarray(a) for a in shifted], size, size, eps2d=0.0)["image"]
        checks["ours_matched_vs_oracle_matched"] = psnr(matched, oracle)
        checks.update({f"{name}_vs_oracle_matched": psnr(img, oracle) for name, img in splax_images.items()})
    return checks


def _summary(rows: dict) -> dict:
    """Ours' fastest variant against splax's fastest exact variant and its defaults."""
    out = {}
    for stage in ("forward", "forward_backward"):
        key = f"{stage}_median_s"
        timed = {n: r[key] for n, r in rows.items() if key in r}
        ours = min((n for n in timed if n.startswith("ours")), key=timed.get)
        exact = [n for n in timed if n.startswith("splax_exact")]
        out[f"ours_best_{stage}"] = ours
        if exact:
            best = min(exact, key=timed.get)
            out[f"splax_best_exact_{stage}"] = best
            out[f"speedup_{stage}_vs_splax_exact"] = timed[best] / timed[ours]
        if "splax_default" in timed:
            out[f"speedup_{stage}_vs_splax_default"] = timed["splax_default"] / timed[ours]
    return out


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--splax-src", required=True, help="splax's src folder (the one holding splax/)")
    parser.add_argument("--splax-revision", default=None, help="splax's commit, recorded in the JSON")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 50_000, 100_000])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--our-tiles", type=int, nargs="+", default=[8], help="our tile sizes (config default 8)")
    parser.add_argument("--chunk-size", type=int, default=16)
    parser.add_argument("--splax-tiles", type=int, nargs="+", default=[8, 16, 40],
                        help="splax tile sizes run with nothing dropped")
    parser.add_argument("--repeats", type=int, default=5, help="alternating timing rounds")
    parser.add_argument("--max-bytes", type=float, default=4e9,
                        help="skip timing a program whose XLA peak-memory estimate is larger")
    parser.add_argument("--oracle-max-gaussians", type=int, default=10_000,
                        help="float64 oracle PSNR on cells with at most this many Gaussians (0: never)")
    parser.add_argument("--no-splax-patch", action="store_true",
                        help="run splax as it is (its covariance then uses Gaussians 0-2's scales for all)")
    parser.add_argument("--quick", action="store_true", help="the issue's cell only: 50k Gaussians at 256²")
    parser.add_argument("--out", default=None, help="JSON file (default benchmarks/results/peers/peer_<date>.json)")
    args = parser.parse_args(argv)
    for option in ("gaussians", "sizes", "our_tiles", "splax_tiles"):
        if min(getattr(args, option)) <= 0:
            parser.error(f"--{option.replace('_', '-')} must be positive integers")
    if args.repeats <= 0 or args.chunk_size <= 0:
        parser.error("--repeats and --chunk-size must be positive")
    if args.quick:
        args.gaussians, args.sizes = [50_000], [256]
    return args


def main(argv=None):
    args = parse_args(argv)
    try:
        splax, jaxlie, digests, patches = load_splax(args.splax_src, patch=not args.no_splax_patch)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    load_before = os.getloadavg()
    cells = [measure_cell((splax, jaxlie), num, size, args) for num in args.gaussians for size in args.sizes]
    report = dict(
        benchmark="peer_splax", date=datetime.date.today().isoformat(),
        jax=jax.__version__, backend=jax.default_backend(), device=str(jax.devices()[0]),
        machine=platform.machine(), cpu_count=os.cpu_count(), python=platform.python_version(),
        load_average_1min_before_after=[load_before[0], os.getloadavg()[0]],
        splax=dict(source=str(pathlib.Path(args.splax_src).resolve()), revision=args.splax_revision,
                   sha256_16=digests, mode="jax", patches=patches),
        timing="median over alternating rounds (each program called once per round, rotating order)",
        loss="sum(image * w), w ~ N(0, 1) fixed (seed 1); gradient w.r.t. means, quats, scales, opacities, colors",
        conventions=CONVENTIONS, repeats=args.repeats, cells=cells,
    )
    text = json.dumps(report, indent=1)
    out = pathlib.Path(args.out) if args.out else RESULTS / f"peer_{report['date']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n", encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
