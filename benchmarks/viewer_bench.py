"""Viewer frame time per mode, and the training slowdown of ``train.viewer=true``; prints JSON.

    PYTHONPATH=src python benchmarks/viewer_bench.py [--run RUN_DIR] [--frames 5] [--slowdown] [--out FILE]

Frame time: the viewer's own render path (:class:`cusgs_jax.view.render.ViewRenderer` + the mode's
colouring, :func:`cusgs_jax.view.modes.colourise`) at the first training camera, median of
``--frames`` renders after a warm-up (compilation excluded), at 320×240 and 640×480. Without
``--run`` a small run is trained first (demo scene 80×60, 8 views, 200 steps, the semantic and
daisy feature models).

``--slowdown``: the same small training (300 steps) twice, once plain and once with
``train.viewer=true`` and a headless Chromium (playwright) showing the live view the whole time;
reports the training clocks (``train_wall_s`` of eval.json: the steps only, never the view), the
wall times of the whole runs, and the live view's own account (frames, share of the loop's wall time).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import shutil
import statistics
import tempfile
import threading
import time

from cusgs_jax.run_folder import read_eval

SIZES = ((320, 240), (640, 480))


def _train(root: pathlib.Path, iterations: int, *extra: str) -> tuple[pathlib.Path, float]:
    from cusgs_jax.app.run import run
    from cusgs_jax.compose import compose_config
    from cusgs_jax.data.demo import generate_demo_scene

    scene = root / "scene"
    if not scene.exists():
        generate_demo_scene(scene, num_views=8, width=80, height=60, num_points=3000)
    out = root / f"run{len(list(root.glob('run*')))}"
    cfg = compose_config([f"data.path={scene}", f"train.iterations={iterations}", "train.progress=false",
                          "eval.every=0", "eval.save_renders=false", "train.checkpoint_every=0",
                          "features.models=[{name: semantic}, {name: daisy}]", "features.sample_pixels=500",
                          *extra])
    start = time.perf_counter()
    run(cfg, out)
    return out, time.perf_counter() - start


def frame_times(run_dir, frames: int) -> dict:
    from cusgs_jax.io.load_run import load_trained
    from cusgs_jax.view.camera import from_viser, to_viser
    from cusgs_jax.view.modes import colourise, feature_of_mode, mode_names
    from cusgs_jax.view.render import ViewRenderer, from_trained

    model = from_trained(load_trained(run_dir))
    renderer = ViewRenderer(model.cfg)
    _, K, viewmat, _, height = model.cameras[0]
    wxyz, position, fov = to_viser(K, viewmat, height)
    out = {}
    for width, h in SIZES:
        camera = from_viser(wxyz, position, fov, width, h)
        row = {}
        for mode in mode_names(model.feature_models):
            feats = feature_of_mode(mode) is not None
            frame = renderer.render(model, camera, features=feats)  # warm-up: compile, grow pair capacity
            query = frame.features[feature_of_mode(mode)][h // 2, width // 2] if mode.startswith("query") else None
            times = []
            for _ in range(frames):
                start = time.perf_counter()
                colourise(mode, renderer.render(model, camera, features=feats), query)
                times.append(1e3 * (time.perf_counter() - start))
            row[mode] = round(statistics.median(times), 1)
        out[f"{width}x{h}"] = row
    return dict(anchors=int(model.anchors.alive.sum()), gaussians_max=int(model.anchors.capacity) * model.cfg.model.n_offsets,
                frame_ms=out)


def slowdown(root: pathlib.Path, iterations: int) -> dict:
    """Training wall time without and with the live view (a headless Chromium watching it throughout)."""
    from playwright.sync_api import sync_playwright

    plain_dir, plain_s = _train(root, iterations)
    port = 8765
    stop = threading.Event()

    def watch():  # a browser on the live view as soon as it listens, until training ends
        import urllib.request

        while not stop.is_set():
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=shutil.which("chromium"),
                                        args=["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport=dict(width=640, height=480))
            page.goto(f"http://127.0.0.1:{port}")
            stop.wait()
            browser.close()

    import logging

    said = []
    handler = logging.Handler()
    handler.emit = lambda record: said.append(record.getMessage())
    logging.getLogger("cusgs_jax").addHandler(handler)
    logging.getLogger("cusgs_jax").setLevel(logging.INFO)
    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    try:
        live_dir, live_s = _train(root, iterations, "train.viewer=true", f"train.viewer_port={port}")
    finally:
        stop.set()
        thread.join(timeout=30)
        logging.getLogger("cusgs_jax").removeHandler(handler)
    plain = read_eval(plain_dir).train_wall_s  # the run-folder contract (cusgs_jax/run_folder.py)
    live = read_eval(live_dir).train_wall_s
    return dict(iterations=iterations, train_wall_s_plain=round(plain, 2), train_wall_s_live_steps_only=round(live, 2),
                run_s_plain=round(plain_s, 2), run_s_live=round(live_s, 2),
                slowdown_of_the_whole_run=round(live_s / plain_s - 1.0, 3),
                live_view_log=[m for m in said if m.startswith("live viewer")])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None, help="a run folder (default: train a small one)")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--slowdown", action="store_true", help="also measure train.viewer=true's training slowdown")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args()
    import jax

    with tempfile.TemporaryDirectory() as tmp:
        root = pathlib.Path(tmp)
        run_dir = pathlib.Path(args.run) if args.run else _train(root, 200)[0]
        result = dict(device=str(jax.devices()[0]), cpu=platform.processor() or platform.machine(),
                      run="given" if args.run else "demo 80x60, 8 views, 200 steps, semantic + daisy",
                      **frame_times(run_dir, args.frames))
        if args.slowdown:
            result["training_with_live_view"] = slowdown(root, 300)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
