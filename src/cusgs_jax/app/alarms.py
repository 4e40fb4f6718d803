"""Warnings about a loss term far outside its normal range: a scene or target problem says so at once."""

from __future__ import annotations

import logging
import math

log = logging.getLogger("cusgs_jax")

LOSS_ALARM = 1.0  # 0.8·L1 + 0.2·(1 − SSIM) of images in [0, 1] starts near 0.3 and stays below ~1
FEATURE_L2_ALARM = 100.0  # mean squared error per feature component; the extractors' targets keep it below ~10


def loss_alarms(alarmed: set[str], step: int, metrics: dict) -> None:
    """Warn (once per loss term and run) when a logged step's loss term is far outside its normal range.

    Every term of ``metrics`` is looked at: the image loss (:data:`LOSS_ALARM`), each feature model's
    L2 term (:data:`FEATURE_L2_ALARM`) and any term that is not finite.
    """
    for key, value in metrics.items():
        if not key.startswith("loss") or key in alarmed:
            continue
        value = float(value)
        if key == "loss_image" and value > LOSS_ALARM:
            log.warning("step %d: image loss %.4g is far above the normal range (< %g for images in [0, 1]): check "
                        "the scene (poses, images) and model.voxel_size / loss.volume_weight, which are in units of "
                        "the scene extent", step, value, LOSS_ALARM)
        elif key.startswith("loss_feat_") and key.endswith("_l2") and value > FEATURE_L2_ALARM:
            name = key[len("loss_feat_"):-len("_l2")]
            log.warning("step %d: the L2 feature loss of model %s is %.4g, far above the normal range (< %g for "
                        "the targets the extractors produce): its target maps (features/%s/ of the scene) hold "
                        "values far too large (a stray value or a scale factor; see the warning on their norms at "
                        "load); fix or re-extract them with cusgs-extract", step, name, value, FEATURE_L2_ALARM,
                        name)
        elif not math.isfinite(value):
            log.warning("step %d: the loss term %s is %s (the step's update was skipped): learning rates far too "
                        "large (optim.*) diverge this way; otherwise check the scene's images and feature targets "
                        "for non-finite values", step, key.removeprefix("loss_") or key, value)
        else:
            continue
        alarmed.add(key)


SKIPPED_LIMIT = 0.5  # a run that skipped more than this share of its updates did not train: refused at its end


def require_trained(skipped: int, steps: int, record: str) -> None:
    """UserError (exit 2) when more than :data:`SKIPPED_LIMIT` of the ``steps`` updates were skipped because the
    loss or a gradient was not finite: the model did not train, whatever its record (``record``) says."""
    if steps and skipped > SKIPPED_LIMIT * steps:
        from cusgs_jax.errors import UserError

        raise UserError(f"{skipped} of {steps} updates were skipped because the loss or a gradient was not finite: "
                        f"the model did not train ({record} records it). Learning rates far too large (optim.*, e.g. "
                        "optim.offsets, optim.appearance) diverge this way; lower them, or check the scene's images "
                        "and feature targets for non-finite values")
