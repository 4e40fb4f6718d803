"""A training loop of one's own, written from cusgs-jax's public pieces (docs/api.md#a-loop-of-your-own).

The loop ``cusgs-train`` runs, step for step: its held-out numbers come out the same to the last digit. Change
what you study — the view order, when the strategies run, what is logged, an extra loss term (``loss_terms=``) —
and keep the rest.

    python examples/own_loop.py [OVERRIDES ...] [--out DIR]     # e.g. train.iterations=500 data.path=/scenes/x
"""

from __future__ import annotations

import argparse
import json
import logging
import pathlib

import cusgs_jax as cg


def main(argv=None, loss_terms=()) -> cg.EvalRecord:
    """Train with the overrides of ``argv`` (``cusgs-train``'s) in ``--out``; returns the run's record."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="cusgs-train overrides, e.g. train.iterations=500")
    parser.add_argument("--out", default="outputs/own_loop", help="the run folder (written as cusgs-train's)")
    args = parser.parse_args(argv)

    cfg = cg.compose_config(args.overrides)  # the configuration cusgs-train would run
    session = cg.setup(cfg, args.out, loss_terms=loss_terms)  # the scene read once, auto settings resolved
    loop = cg.start(session)  # train state and optimiser; work capacities fitted to the training views
    cfg, last = session.cfg, session.cfg.train.iterations  # resolved for the scene (voxel size, ...)
    with open(pathlib.Path(args.out) / "own_log.jsonl", "w") as log_file:
        for step in range(int(loop.state.step), last):
            done = step + 1
            with session.budget.clock:  # the training clock of the held-out curve (eval.json's train_wall_s)
                # one jitted step on this step's view; a view that overflows a capacity grows it and is replayed
                metrics = cg.exact_step(session, loop, session.batches(step))
                cg.run_strategies(session, loop, done)  # the growing and pruning passes that are due
            if done % cfg.train.log_every == 0:  # every loss term, weighted (they sum to the loss)
                terms = {name: float(value) for name, value in metrics["terms"].items()}
                log_file.write(json.dumps(dict(step=done, loss=float(metrics["loss"]), **terms)) + "\n")
            if cfg.eval.every and (done % cfg.eval.every == 0 or done == last):
                point = cg.curve_point(session, loop, done)  # held-out PSNR of the model as it is now
                print(f"step {done}: held-out PSNR {point['psnr']:.2f} dB, {point['alive_anchors']} anchors")
    cg.save_checkpoint(session, loop, last)  # resumable, and what cusgs-export / cusgs-view read
    record = cg.finalise(session, loop)  # held-out PSNR / SSIM / LPIPS, eval.json, renders, plot
    print(f"held-out PSNR {record.psnr!r}, SSIM {record.ssim!r}, LPIPS {record.lpips_vgg!r}, "
          f"{record.alive_anchors} anchors")
    return record


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    main()
