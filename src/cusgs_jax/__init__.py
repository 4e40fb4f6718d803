"""cusgs-jax: CUS-GS (compact unified structured Gaussian splatting) in JAX.

The pure pieces, for research code composing its own jitted steps
(shapes: A anchors, N offsets, G = A·N Gaussians, H×W images):

* :func:`init_anchors`, :func:`voxelize` — scaffold from SfM points (``scaffold``)
* :func:`init_decoder`, :func:`decode_gaussians`, :func:`frustum_mask` — anchors → Gaussians (``decode``)
* :func:`rasterize`, :func:`rasterize_batch` — differentiable splatting (``splat``)
* ``losses`` — L1, SSIM, volume regulariser, :func:`losses.image_loss`
* :func:`accumulate_stats`, :func:`adjust_anchors` — growing and pruning (``grow_prune``)
* :func:`accumulate_prune_stats`, :func:`prune_pass`, :class:`PruneConfig` — feature-aware pruning (``prune``)
* :func:`make_train_step`, :func:`make_prune_step`, :func:`init_train_state` — the full step and the
  pruning pass between steps (``train``)
* :func:`load_scene`, :func:`demo_scene_path` — data (``data``)
"""

from cusgs_jax import losses, metrics
from cusgs_jax.data.colmap import SceneData, SceneError, load_scene
from cusgs_jax.data.demo import demo_scene_path, generate_demo_scene
from cusgs_jax.decode import DecoderConfig, Gaussians, decode_gaussians, frustum_mask, init_decoder
from cusgs_jax.grow_prune import GrowConfig, GrowStats, accumulate_stats, adjust_anchors
from cusgs_jax.prune import PruneConfig, PruneStats, accumulate_prune_stats, anchor_scores, prune_pass
from cusgs_jax.scaffold import AnchorParams, Anchors, init_anchors, voxelize
from cusgs_jax.splat import RenderOutput, check_inputs, rasterize, rasterize_batch
from cusgs_jax.train import TrainConfig, TrainState, init_train_state, make_prune_step, make_train_step

__version__ = "0.1.0"
__all__ = [
    "AnchorParams", "Anchors", "DecoderConfig", "Gaussians", "GrowConfig", "GrowStats", "PruneConfig", "PruneStats",
    "RenderOutput",
    "SceneData", "SceneError", "TrainConfig", "TrainState", "accumulate_prune_stats", "accumulate_stats",
    "adjust_anchors", "anchor_scores",
    "check_inputs", "decode_gaussians", "demo_scene_path", "frustum_mask", "generate_demo_scene",
    "init_anchors", "init_decoder", "init_train_state", "load_scene", "losses", "make_prune_step", "make_train_step",
    "metrics", "prune_pass",
    "rasterize", "rasterize_batch", "voxelize",
]
