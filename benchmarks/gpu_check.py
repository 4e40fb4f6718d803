"""One command for a machine with an NVIDIA GPU: tests, the compositors and splax, the README's main job; prints JSON.

Runs the parts named by ``--parts`` (default: tests, splatter, main_job, sweep) in the order below,
each in a subprocess with its own time limit (together at most ``--budget`` seconds, 8 minutes by
default; ``--part-seconds tests=200`` caps one part; a part stopped at its limit gets SIGINT first,
so pytest still reports what it finished):

1. **pallas_tests** — ``tests/splat/test_composite_pallas.py`` on the GPU (the Triton kernels themselves);
2. **splatter** — ``splat_bench.py`` at the issue's cells (50k Gaussians at 256², 500k and 1M at
   1024², tile 8 and 16, or ``--cells``; forward and forward+backward medians) with each compositor of
   ``--backends`` side by side and, given ``--splax-src``, ``peer_bench.py --quick`` (splax at 50k, 256²);
3. **train_step** — ``train_bench.py``: the demo's step with each compositor at ``--pixel-factors``;
   **train_target** — the same on scale_bench.py's target scene (``train_bench.py --target``);
4. **tests** — ``pytest -m "not slow"`` of ``tests/splat``, ``tests/model``, ``tests/training`` and
   ``tests/test_precision.py`` with ``--workers`` xdist workers on the default backend (the GPU),
   ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` so the workers share the card;
5. **main_job** — ``cusgs-train`` with no overrides (the README's main job; 3000 steps, evaluation,
   report) into ``OUT/main_job``, then the same again into ``OUT/main_job_rerun`` (the persistent
   compilation cache warm; ``main_job_once``: the first alone): each run's process wall,
   ``eval.json``'s ``time`` budget, ``compilations`` and held-out PSNR;
6. **sweep** — a two-job Hydra joblib sweep (``train.seed=0,1``, ``--sweep-steps`` steps each) on the
   one device: both jobs must finish, each with the memory fraction the sweep gave it.

Writes ``OUT/gpu_check.json`` (everything) and the logs beside it, and prints a short table last.
``OUT`` is ``--out`` (default ``$OUT`` — the device tool's folder that comes back — else
``gpu_check_out/``). ``--smoke`` shrinks every part (one test module, 10k Gaussians at 64²,
a 40-step main job on a small demo) so the script itself can be checked on a CPU.

    python benchmarks/gpu_check.py [--splax-src splax/src] [--budget 480]
    python benchmarks/gpu_check.py --smoke        # on a CPU: the script works
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

from cusgs_jax.run_folder import read_eval

ROOT = pathlib.Path(__file__).resolve().parent.parent
TRAIN = [sys.executable, "-c", "import sys; from cusgs_jax.app.train import main; sys.argv[0] = 'cusgs-train'; main()"]
TEST_PATHS = ["tests/splat", "tests/model", "tests/training", "tests/test_precision.py"]
SPLAT_CELLS = [(50_000, 256, (8, 16)), (500_000, 1024, (8, 16)), (1_000_000, 1024, (8, 16))]
SMOKE_MAIN = ["train.iterations=40", "eval.every=20", "data.demo.views=8", "data.demo.width=80", "data.demo.height=60"]


def _run(cmd, log: pathlib.Path, timeout: float, env=None) -> dict:
    """Run ``cmd`` with stdout+stderr into ``log``; {"rc", "wall_s", "timed_out"}.

    At the time limit the process gets SIGINT first (pytest then prints the summary of the tests it
    finished) and SIGKILL 20 s later."""
    start = time.perf_counter()
    with open(log, "w") as out:
        process = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                                   env={**os.environ, **(env or {})})
        try:
            rc, timed_out = process.wait(timeout=max(timeout, 1)), False
        except subprocess.TimeoutExpired:
            timed_out = True
            process.send_signal(signal.SIGINT)
            try:
                rc = process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                rc = process.wait()
    return dict(rc=rc, wall_s=round(time.perf_counter() - start, 2), timed_out=timed_out, log=log.name)


def run_tests(out: pathlib.Path, workers: int, timeout: float, smoke: bool, paths=None, name="tests",
              markers: str | None = "not slow") -> dict:
    paths = paths or (["tests/test_precision.py"] if smoke else TEST_PATHS)
    cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", *(["-m", markers] if markers else []), "-p",
           "no:cacheprovider", "-p", "no:benchmark", *paths]
    if workers > 1:
        cmd += ["-n", str(workers)]
    result = _run(cmd, out / f"{name}.log", timeout, env={"XLA_PYTHON_CLIENT_PREALLOCATE": "false"})
    text = (out / f"{name}.log").read_text(errors="replace")
    summary = [line for line in text.splitlines() if re.search(r"\d+ (passed|failed)", line)]
    result["summary"] = summary[-1].strip("= ") if summary else None
    for key in ("passed", "failed", "skipped", "errors"):
        found = re.search(rf"(\d+) {key.rstrip('s') if key == 'errors' else key}", result["summary"] or "")
        result[key] = int(found.group(1)) if found else 0
    result["failures"] = [line[7:] for line in text.splitlines() if line.startswith("FAILED ")][:40]
    return result


def _cells(specs: list[str]) -> list[tuple[int, int, tuple[int, ...]]]:
    """"500000:1024:8,16" → (500000, 1024, (8, 16))."""
    cells = []
    for spec in specs:
        num, size, tiles = spec.split(":")
        cells.append((int(num), int(size), tuple(int(t) for t in tiles.split(","))))
    return cells


def run_splatter(out: pathlib.Path, timeout: float, smoke: bool, splax_src: str | None, cells=None,
                 backends=("jax",)) -> dict:
    cells = [(10_000, 64, (8, 16))] if smoke else (cells or SPLAT_CELLS)
    rows, runs, deadline = [], [], time.perf_counter() + timeout
    for num, size, tiles in cells:
        log = out / f"splat_{num}_{size}.log"
        cmd = [sys.executable, "benchmarks/splat_bench.py", "--gaussians", str(num), "--sizes", str(size),
               "--tile-sizes", *map(str, tiles), "--repeats", "3" if smoke else "5", "--backends", *backends]
        runs.append(_run(cmd, log, deadline - time.perf_counter()))
        text = log.read_text(errors="replace")
        try:
            rows += json.loads(text[text.index("{\n"):])["results"]
        except ValueError:  # stopped early: the rows it printed as it went
            rows += [json.loads(line) for line in text.splitlines() if line.startswith('{"renderer"')]
    result = dict(runs=runs, ours=[{k: r.get(k) for k in ("backend", "gaussians", "width", "tile_size",
                                                           "forward_median_s", "forward_backward_median_s",
                                                           "forward_compile_s", "forward_backward_compile_s",
                                                           "composited_pairs", "forward_backward_pairs_per_s",
                                                           "image_rel_diff", "grad_rel_diff", "error")} for r in rows])
    if splax_src:
        peer_json = out / "peer.json"
        cmd = [sys.executable, "benchmarks/peer_bench.py", "--splax-src", splax_src, "--our-tiles", "8", "16",
               "--splax-tiles", "16", "--out", str(peer_json)] + (["--gaussians", "10000", "--sizes", "64"]
                                                                   if smoke else ["--quick"])
        result["peer_run"] = _run(cmd, out / "peer.log", deadline - time.perf_counter())
        if peer_json.is_file():
            result["peer"] = json.loads(peer_json.read_text())
    else:
        result["peer"] = "skipped: no --splax-src (git clone https://github.com/chungmin99/splax; jaxlie, jax_dataclasses)"
    return result


def run_train_step(out: pathlib.Path, timeout: float, smoke: bool, backends, pixel_factors,
                   target: bool = False) -> dict:
    """``train_bench.py``: the demo's (or with ``target`` the target scene's) train step with each compositor,
    steps interleaved."""
    log = out / ("train_target.log" if target else "train_step.log")
    sizes = ["--pixel-factors", "1"] if smoke else (["--target"] if target else
                                                     ["--pixel-factors", *map(str, pixel_factors)])
    cmd = [sys.executable, "benchmarks/train_bench.py", "--steps", "3" if smoke else "20", "--views",
           "4" if smoke else "12", *sizes, "--backends", *backends]
    result = _run(cmd, log, timeout)
    text = log.read_text(errors="replace")
    rows = [json.loads(line) for line in text.splitlines() if line.startswith('{"pixel_factor"')]
    result["errors"] = [line[:2500] for line in text.splitlines() if line.startswith('{"backend"')]
    result["rows"] = [{k: r.get(k) for k in ("backend", "width", "height", "anchors", "compile_s",
                                             "median_step_s", "ratio")} for r in rows]
    return result


def run_main_job(out: pathlib.Path, name: str, timeout: float, smoke: bool) -> dict:
    folder = out / name
    cmd = [*TRAIN, f"hydra.run.dir={folder}", "train.progress=false", *(SMOKE_MAIN if smoke else [])]
    result = _run(cmd, out / f"{name}.log", timeout)
    data = read_eval(folder)  # the run-folder contract (cusgs_jax/run_folder.py)
    if data is not None:
        compiles = data.get("compilations", {})
        result.update(psnr=data.psnr, ssim=data.ssim, time=data.get("time"),
                      compilations={k: compiles.get(k) for k in ("count", "compiled", "from_cache", "seconds",
                                                                 "backend_seconds", "train_step",
                                                                 "evaluation_renders", "functions")},
                      budget_over_wall=round(data.time["total"] / result["wall_s"], 4) if data.get("time") else None,
                      accelerator=data.get("accelerator"))
    return result


def run_sweep(out: pathlib.Path, steps: int, timeout: float, smoke: bool) -> dict:
    """Two jobs of one joblib sweep side by side on the default device (issue 29: one GPU, several jobs)."""
    folder = out / "sweep"
    cmd = [*TRAIN, "-m", "train.seed=0,1", f"train.iterations={steps}", f"eval.every={max(steps // 2, 1)}",
           "train.progress=false", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={folder}",
           *(SMOKE_MAIN[2:] if smoke else [])]
    result = _run(cmd, out / "sweep.log", timeout)
    jobs = []
    for job in ("0", "1"):
        data = read_eval(folder / job)
        if data is not None:
            jobs.append(dict(job=job, psnr=data.psnr, accelerator=data.get("accelerator"),
                             total_s=(data.get("time") or {}).get("total")))
        else:
            jobs.append(dict(job=job, finished=False))
    result["jobs"] = jobs
    result["both_finished"] = all("psnr" in job for job in jobs)
    return result


def table(report: dict) -> str:
    lines = [f"gpu_check on {report['device']} (jax {report['jax']}, {report['backend']})"]
    tests = report.get("tests")
    if tests:
        lines.append(f"tests: {tests['summary']} in {tests['wall_s']:.0f} s"
                     + (" (stopped at its time limit)" if tests["timed_out"] else ""))
        lines += [f"  FAILED {name}" for name in tests["failures"][:10]]
    pallas = report.get("pallas_tests")
    if pallas:
        lines.append(f"pallas tests: {pallas['summary']} in {pallas['wall_s']:.0f} s"
                     + (" (stopped at its time limit)" if pallas["timed_out"] else ""))
        lines += [f"  FAILED {name}" for name in pallas["failures"][:10]]
    splat = report.get("splatter")
    if splat:
        lines.append("splatter (ms)                   fwd   fwd+bwd   rel.diff img / grad")
        for row in splat["ours"]:
            if row.get("error"):
                lines.append(f"  {row.get('backend')} {row['gaussians']} {row['width']}² t{row['tile_size']}: "
                             f"{row['error'][:300]}")
            if row.get("forward_median_s"):
                diff = (f"{row['image_rel_diff']:.1e} / {row['grad_rel_diff']:.1e}"
                        if row.get("image_rel_diff") is not None else "")
                lines.append(f"  {row.get('backend', 'jax'):<7}{row['gaussians']:>8} {row['width']:>5}² "
                             f"t{row['tile_size']:<3}{1e3 * row['forward_median_s']:8.2f} "
                             f"{1e3 * row['forward_backward_median_s']:8.2f}   {diff}")
        peer = splat.get("peer")
        if isinstance(peer, dict):
            for cell in peer.get("cells", peer.get("results", []))[:4]:
                lines.append(f"  splax {json.dumps(cell)[:150]}")
    for name, scene in (("train_step", "demo"), ("train_target", "target scene")):
        step = report.get(name)
        if not step:
            continue
        lines.append(f"train step ({scene}, ms): rc {step['rc']}")
        lines += [f"  error {line[:300]}" for line in step.get("errors", [])]
        for row in step["rows"]:
            lines.append(f"  {row['backend']:<7}{row['width']}x{row['height']} anchors {row['anchors']}: "
                         f"{1e3 * row['median_step_s']:.2f} ms (x{row['ratio']:.2f}), compile {row['compile_s']:.1f} s")
    for name in ("main_job", "main_job_rerun"):
        job = report.get(name)
        if job and job.get("time"):
            c = job["compilations"]
            lines.append(f"{name}: wall {job['wall_s']:.0f} s, budget {job['time']['total']:.0f} s, PSNR "
                         f"{job['psnr']:.2f} dB; {c['count']} compilations {c['seconds']:.1f} s (backend "
                         f"{c['backend_seconds']:.1f} s, {c['from_cache']} from cache), train step "
                         f"{c['train_step']}, eval renders {c['evaluation_renders']}")
            stages = sorted(((k, v) for k, v in job["time"].items() if k != "total"), key=lambda kv: -kv[1])
            lines.append("  " + ", ".join(f"{k} {v:.1f}" for k, v in stages if v >= 0.1))
        elif job:
            lines.append(f"{name}: rc {job['rc']}, timed out {job['timed_out']} (log {job['log']})")
    sweep = report.get("sweep")
    if sweep:
        lines.append(f"sweep (2 jobs, one device): rc {sweep['rc']}, wall {sweep['wall_s']:.0f} s, both finished "
                     f"{sweep['both_finished']}; " + "; ".join(
                         f"job {j['job']}: PSNR {j['psnr']:.2f}, memory fraction "
                         f"{(j['accelerator'] or {}).get('memory_fraction')}" if "psnr" in j else f"job {j['job']}: -"
                         for j in sweep["jobs"]))
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.environ.get("OUT") or "gpu_check_out")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds for all parts together")
    parser.add_argument("--workers", type=int, default=8, help="pytest-xdist workers for the tests")
    parser.add_argument("--splax-src", default=None, help="splax's src folder (peer_bench.py); none: splax skipped")
    parser.add_argument("--parts", nargs="+", default=["tests", "splatter", "main_job", "sweep"],
                        choices=["pallas_tests", "splatter", "train_step", "train_target", "tests", "main_job",
                                 "main_job_once", "sweep"],
                        help="main_job: cold then warm cache; main_job_once: the cold run alone")
    parser.add_argument("--backends", nargs="+", default=["jax"], choices=["auto", "jax", "pallas"],
                        help="compositors the splatter and train-step parts time")
    parser.add_argument("--cells", nargs="+", default=None, metavar="G:SIZE:TILES",
                        help="splatter cells, e.g. 500000:1024:8,16 (default: the issue's)")
    parser.add_argument("--pixel-factors", nargs="+", type=int, default=[1, 4], help="train-step image sizes")
    parser.add_argument("--part-seconds", nargs="+", default=[], metavar="PART=S",
                        help="time limit of a part, e.g. tests=200 (default: shares of --budget)")
    parser.add_argument("--sweep-steps", type=int, default=600, help="steps of each of the sweep's two jobs")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script on a CPU")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    import jax

    report = dict(benchmark="gpu_check", jax=jax.__version__, backend=jax.default_backend(),
                  device=str(jax.devices()[0]), smoke=args.smoke, budget_s=args.budget)
    deadline = time.perf_counter() + args.budget
    shares = {"tests": 0.3, "splatter": 0.3, "main_job": 0.3}  # of the budget, in this order; leftovers carry over
    left = lambda: deadline - time.perf_counter()  # noqa: E731

    limits = {k: float(v) for k, v in (item.split("=") for item in args.part_seconds)}

    def limit(part: str, default: float) -> float:
        return min(left(), limits.get(part, default))

    def save(part: str) -> None:  # after every part, so a run stopped at its limit still brings its numbers back
        (out / "gpu_check.json").write_text(json.dumps(report, indent=1))
        print(f"[gpu_check] {part} done, {left():.0f} s of the budget left", flush=True)

    if "pallas_tests" in args.parts:
        report["pallas_tests"] = run_tests(out, min(args.workers, 4), limit("pallas_tests", 0.15 * args.budget),
                                           args.smoke, ["tests/splat/test_composite_pallas.py"], "pallas_tests",
                                           markers=None)  # the slow ones too: fast on a GPU
        save("pallas_tests")
    if "splatter" in args.parts:
        report["splatter"] = run_splatter(out, limit("splatter", shares["splatter"] * args.budget + 30), args.smoke,
                                          args.splax_src, _cells(args.cells) if args.cells else None,
                                          tuple(args.backends))
        save("splatter")
    if "train_step" in args.parts:
        report["train_step"] = run_train_step(out, limit("train_step", 0.25 * args.budget), args.smoke,
                                              args.backends, args.pixel_factors)
        save("train_step")
    if "train_target" in args.parts:
        report["train_target"] = run_train_step(out, limit("train_target", 0.3 * args.budget), args.smoke,
                                                args.backends, args.pixel_factors, target=True)
        save("train_target")
    if "tests" in args.parts:
        report["tests"] = run_tests(out, args.workers, limit("tests", shares["tests"] * args.budget), args.smoke)
        save("tests")
    if "main_job" in args.parts or "main_job_once" in args.parts:
        report["main_job"] = run_main_job(out, "main_job", left() * 0.6, args.smoke)
        save("main_job")
        if "main_job" in args.parts:
            report["main_job_rerun"] = run_main_job(out, "main_job_rerun", left() * (0.5 if "sweep" in args.parts
                                                                                      else 1.0), args.smoke)
            save("main_job_rerun")
    if "sweep" in args.parts:
        report["sweep"] = run_sweep(out, 40 if args.smoke else args.sweep_steps, left(), args.smoke)
        save("sweep")
    print(json.dumps(report, indent=1))
    print(table(report))
    return report


if __name__ == "__main__":
    main()
