"""``cusgs_jax.render`` (jitted, vmapped over the held-out views) against four sequential calls of the run's
evaluation render (``training.render.make_render_fn``), timed alternately in one process; prints JSON.

    python benchmarks/render_api.py RUN_DIR [--rounds 20]

Also reports whether the images are identical and the PSNR each path gives against the held-out images, beside
``eval.json``'s (the held-out protocol: the nearest training camera's appearance embedding).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

import cusgs_jax as cg
from cusgs_jax.eval.metrics import psnr
from cusgs_jax.rendering import appearance_index
from cusgs_jax.training.inputs import load_data
from cusgs_jax.training.render import make_render_fn
from cusgs_jax.types import Camera


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args(argv)

    model = cg.load_trained(args.run)
    scene, _ = load_data(model.cfg)
    views = [int(v) for v in scene.test_indices]
    cameras = cg.stack_cameras([Camera.of_scene(scene, v) for v in views])
    apps = [appearance_index("nearest", np.asarray(scene.camera_centers[scene.train_indices]),
                                          np.asarray(scene.camera_centers[v])) for v in views]
    targets = [scene.images[v].astype(np.float32) / 255.0 for v in views]

    old = make_render_fn(model.cfg)  # today's evaluation render: host-side, grows its capacities on demand
    single = [Camera.of_scene(scene, v) for v in views]

    def sequential():
        return [np.asarray(jax.block_until_ready(old(model.anchors, model.nets, cam, app)[0]))
                for cam, app in zip(single, apps)]

    capacities = cg.fit_render(model, cameras)
    batched = jax.jit(jax.vmap(lambda camera: cg.render(model, camera, capacities=capacities)))

    def vmapped():
        return np.asarray(jax.block_until_ready(batched(cameras).image))

    def batch():  # one call with the batch of cameras (views one after another in one program)
        return np.asarray(jax.block_until_ready(cg.render(model, cameras, capacities=capacities).image))

    first_old, first_new, first_batch = sequential(), vmapped(), batch()  # compiles
    paths = {"make_render_fn_x4": sequential, "render_vmap": vmapped, "render_batch": batch}
    times = {name: [] for name in paths}
    for _ in range(args.rounds):  # alternately
        for name, fn in paths.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    medians = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    evaluation = model.evaluation.per_view if model.evaluation else None
    result = dict(run=args.run, views=len(views), size=[scene.width, scene.height],
                  anchors=model.num_anchors, capacities=capacities.as_dict(), rounds=args.rounds,
                  median_ms=medians, ratio_render_over_sequential=medians["render_vmap"] / medians["make_render_fn_x4"],
                  ratio_batch_over_sequential=medians["render_batch"] / medians["make_render_fn_x4"],
                  max_abs_image_difference=float(max(np.max(np.abs(a - b)) for a, b in zip(first_old, first_new))),
                  max_abs_image_difference_batch=float(max(np.max(np.abs(a - b))
                                                           for a, b in zip(first_old, first_batch))),
                  psnr_render=[float(psnr(image, t)) for image, t in zip(first_new, targets)],
                  psnr_make_render_fn=[float(psnr(image, t)) for image, t in zip(first_old, targets)],
                  psnr_eval_json=None if evaluation is None else [row["psnr"] for row in evaluation],
                  backend=jax.default_backend())
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
