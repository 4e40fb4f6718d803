"""cusgs-jax: CUS-GS (compact unified structured Gaussian splatting) in JAX.

A lazy facade: ``import cusgs_jax`` imports nothing heavy; each name below is
imported from its module on first use (so command-line tools that never touch
JAX do not load it). The naming table of array shapes is in :mod:`cusgs_jax.types`.

Data flow of one training step, with the module of each stage::

    scene (data.layouts: colmap, blender, nerfstudio; data.demo) → anchors (model.anchors) → decode (model.decode)
      → splat (splat.render) → loss (losses, model.field) → update (training.step, training.optim)
      → densify (densify.scaffold, densify.feature_prune) → evaluate (eval.views, eval.features)
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    # configuration and types
    "Config": "config", "DataConfig": "config", "ModelConfig": "config", "SplatConfig": "config", "GrowConfig": "config",
    "PruneConfig": "config", "FeatureConfig": "config", "DecoderConfig": "config", "compose_config": "compose",
    "Camera": "types",
    # data
    "SceneData": "data.scene_data", "SceneError": "data.colmap", "load_scene": "data.loader",
    "load_cameras": "data.loader", "SceneCameras": "data.loader", "detect_format": "data.layouts",
    "normalize_scene": "data.normalize", "WorldTransform": "data.normalize",
    "UserError": "errors", "ConfigError": "errors", "CheckpointError": "errors",
    "demo_scene_path": "data.demo", "generate_demo_scene": "data.demo",
    # model
    "AnchorParams": "model.anchors", "AnchorState": "model.anchors", "init_anchors": "model.anchors",
    "voxelize": "model.anchors",
    "Gaussians": "model.decode", "decode_gaussians": "model.decode", "frustum_mask": "model.decode",
    "init_decoder": "model.decode", "decode_view": "model.decode", "ViewInputs": "model.decode",
    "view_inputs": "model.decode", "decode_inputs": "model.decode",
    # splatting
    "RenderOutput": "splat", "check_inputs": "splat", "rasterize": "splat", "rasterize_batch": "splat",
    "sh_to_rgb": "splat", "sh_basis": "splat", "rasterize_jit": "splat", "rasterize_batch_jit": "splat",
    "Compositor": "splat",
    # models that leave the project (standard 3DGS PLY)
    "SplatModel": "io", "PlyError": "io", "read_ply": "io", "write_ply": "io", "render_splats": "io",
    "bake_splats": "model.bake", "load_trained": "io.load_run", "TrainedModel": "io.load_run",
    # densification
    "GrowStats": "densify.scaffold", "accumulate_stats": "densify.scaffold",
    "ScaffoldStrategy": "densify.scaffold",
    "PruneStats": "densify.feature_prune", "accumulate_prune_stats": "densify.feature_prune",
    "anchor_scores": "densify.feature_prune", "prune_pass": "densify.feature_prune",
    "FeaturePruneStrategy": "densify.feature_prune",
    # training
    "TrainState": "training.state", "init_train_state": "training.state",
    "make_train_step": "training.step", "loss_weights": "training.step", "LossTerm": "training.loss_terms",
    "TermRender": "training.loss_terms", "Capacities": "training.capacity", "make_batches": "training.inputs",
    # training from Python: the CLI's run as a function, and the pieces of a loop of one's own (docs/api.md)
    "train": "app.api", "TrainResult": "app.api", "EvalRecord": "run_folder", "read_eval": "run_folder", "setup": "app.session", "Session": "app.session",
    "start": "app.loop", "Loop": "app.loop", "exact_step": "app.loop", "run_strategies": "app.loop",
    "curve_point": "app.loop", "save_checkpoint": "app.loop", "finalise": "app.run",
    # rendering a trained model, cameras and camera paths
    "render": "rendering", "fit_render": "rendering", "Rendered": "rendering",
    "RenderCapacityError": "rendering", "look_at": "cameras", "orbit": "cameras",
    "interpolate_path": "cameras", "pinhole_K": "cameras", "camera_path": "cameras", "from_colmap": "cameras",
    "from_blender": "cameras", "stack_cameras": "cameras",
}
_MODULES = ("losses", "config", "types")

__all__ = sorted([*_EXPORTS, *_MODULES])


def __getattr__(name: str):
    if name in _MODULES:
        return importlib.import_module(f"cusgs_jax.{name}")
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"cusgs_jax.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'cusgs_jax' has no attribute {name!r}")


def __dir__():
    return __all__
