"""``cusgs-train``: the Hydra entry point (a thin shell around :func:`cusgs_jax.runner.run`)."""

from __future__ import annotations

import logging

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from cusgs_jax.data.colmap import SceneError


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    from cusgs_jax.runner import run

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax is chatty at INFO
    output_dir = HydraConfig.get().runtime.output_dir
    try:
        result = run(OmegaConf.to_container(cfg, resolve=True), output_dir)
    except SceneError as error:
        logging.getLogger("cusgs_jax").error("%s", error)
        raise SystemExit(2) from None
    return float(result["psnr"])


if __name__ == "__main__":
    main()
