"""Plots from run outputs (matplotlib, headless): error against training time."""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


#: What the curves' time axis (``wall_s``, the run's training clock, :mod:`cusgs_jax.app.clock`) counts.
CLOCK = ("training steps and densification, the train step's compilations included; evaluation, checkpoints "
         "and set-up excluded")
CLOCK_LABEL = "training wall-clock time (s), step compilation included"


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
