"""Plots from run outputs (matplotlib, headless): error against training time."""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


#: What the curves' time axis (``wall_s``, the run's training clock, :mod:`cusgs_jax.app.clock`; ``eval.json``'s
#: ``train_wall_s`` and ``curve_clock``) counts: the loop's steps and densification (app/loop.py ``train``), with
#: the compiles they waited for inside the loop (a replayed step's, a grown capacity's program). Not on it: the
#: compile of the first step's program, waited for before the loop starts (``eval.json`` ``time.compile_wait``
#: holds it with every other wait), evaluation, checkpoints, the live viewer and set-up.
CLOCK = ("training steps and densification, with the compiles the loop waited for after its first step; the first "
         "step's compile (before the loop), evaluation, checkpoints and set-up excluded")
CLOCK_LABEL = "training time (s): steps and densification, the first step's compile excluded"


def plot_error_vs_time(curve: list[dict], path: pathlib.Path, title: str = "") -> None:
    """Held-out PSNR against training wall-clock seconds.

    Args:
      curve: [{"wall_s": float, "psnr": float, "step": int}, ...].
    """
    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=120)
    if curve:
        ax.plot([c["wall_s"] for c in curve], [c["psnr"] for c in curve], marker="o", ms=3)
        last = curve[-1]
        ax.annotate(f"{last['psnr']:.2f} dB @ step {last['step']}", (last["wall_s"], last["psnr"]),
                    textcoords="offset points", xytext=(-10, -14), ha="right", fontsize=8)
    ax.set_xlabel(CLOCK_LABEL)
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title or "error against run time")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
