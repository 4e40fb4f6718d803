"""``cusgs-train``: the Hydra entry point (a thin shell around :func:`cusgs_jax.app.run.run`).

Single runs: ``cusgs-train model.voxel_size=0.02``. Sweeps:
``cusgs-train -m experiment=voxel_size`` (the ready sweeps are in ``conf/experiment``;
they run side by side with Hydra's joblib launcher). In a sweep a job that raises
writes ``failed.json`` (error and traceback) into its own folder, is logged, and
the other jobs go on; ``cusgs-report <multirun folder>`` lists it as failed.
"""

from __future__ import annotations

import json
import logging
import math
import pathlib
import traceback

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from cusgs_jax.config import from_omegaconf, register_configs
from cusgs_jax.data.colmap import SceneError

log = logging.getLogger("cusgs_jax")
register_configs()  # config.Config is the schema and the defaults of conf/config.yaml


def record_failure(output_dir: str | pathlib.Path, error: BaseException) -> pathlib.Path:
    """Write ``failed.json`` ({"error": "Type: message", "traceback": ...}) into a job folder."""
    path = pathlib.Path(output_dir) / "failed.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "error": f"{type(error).__name__}: {error}",
        "traceback": "".join(traceback.format_exception(type(error), error, error.__traceback__)),
    }, indent=1))
    return path


@hydra.main(version_base="1.3", config_path="pkg://cusgs_jax.conf", config_name="config")
def main(cfg: DictConfig) -> float:
    from cusgs_jax.app.run import run

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax is chatty at INFO
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" at INFO in every job log
    hydra_cfg = HydraConfig.get()
    output_dir = hydra_cfg.runtime.output_dir
    sweeping = hydra_cfg.mode == RunMode.MULTIRUN
    try:
        result = run(from_omegaconf(cfg), output_dir,
                     progress_label=f"job {hydra_cfg.job.num}" if sweeping else "train")
    except SceneError as error:
        record_failure(output_dir, error)
        log.error("%s", error)
        if sweeping:
            return math.nan
        raise SystemExit(2) from None
    except Exception as error:  # noqa: BLE001 - a sweep must outlive one bad job
        if not sweeping:
            raise
        path = record_failure(output_dir, error)
        log.exception("job %s failed (details in %s); the other jobs go on", hydra_cfg.job.num, path)
        return math.nan
    return float(result["psnr"])


if __name__ == "__main__":
    main()
