"""Configuration: frozen dataclasses, the ONLY place a default value is written.

``Config()`` is exactly what ``cusgs-train`` runs with no overrides (the 3000-step demo schedule). Hydra's
schema is built from the same classes (:mod:`cusgs_jax.compose`: the composition, the schema's twins and the
YAML spellings), ``conf/config.yaml`` composes it first, and the YAML group options under ``conf/``
(``grow=scaffold``, ``prune=none``, ``features=demo``, the sweeps) hold only *overrides* of these values.
Configuration is closed over by factories (``make_train_step(cfg, …)``) and never traced; the frozen classes
make that safe. Fields hold what their type says; every ``auto`` (None) is resolved once, in setup, from the
scene (:mod:`cusgs_jax.app.resolve`).

Python code builds configs directly (``Config(model=ModelConfig(voxel_size=0.1))``, ``dataclasses.replace``)
or composes them like the CLI does (:func:`cusgs_jax.compose.compose_config`).
"""

from __future__ import annotations

import dataclasses
import difflib
from typing import Optional

from cusgs_jax.checks import at_least as _at_least, finite_number as _number, lists_to_tuples as _tuples
from cusgs_jax.errors import ConfigError
from cusgs_jax.checks import require, require_config  # noqa: F401  (re-exported: the shell imports them from here)

# M3's split of its 160 query channels when all six models are present (docs/method.md#hierarchical-queries).
M3_QUERY_DIMS = {"clip": 16, "siglip": 32, "dinov2": 32, "seem": 16, "llama3": 32, "llamav": 32}
PRUNE_STRATEGIES = ("feature_aware", "scaffold", "none")
QUERY_GRANULARITIES = ("per_anchor", "per_gaussian")
CAMERA_FRAMES = ("crop", "mask", "lens")  # data.undistort; a scene's camera_frame (data/scene_data.py)
COMPOSITORS = ("auto", "jax", "pallas")  # splat.backend; splat.Compositor.backend (splat/render.py)
MATMUL_PRECISIONS = ("highest", "default")  # model.matmul_precision (cusgs_jax/precision.py)
DATASET_FORMATS = ("colmap", "blender", "nerfstudio")  # data.format, besides "auto" (data/layouts.py)
RANDOM_POINT_RULES = ("cube", "cube_and_rays")  # where random initial points go (data/random_points.py)
RANDOM_INITS = ("auto",) + RANDOM_POINT_RULES  # data.random_init: a rule, or auto (the layout's)


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """The built-in demo scene (used when ``data.path`` is null). ``lens``: the lens it is ray cast
    through (:mod:`cusgs_jax.data.demo.lens`): ``pinhole`` (the demo), ``opencv`` or ``simple_radial``
    (distorted COLMAP cameras, undistorted on load)."""

    views: int = 30
    width: int = 160
    height: int = 120
    seed: int = 0
    lens: str = "pinhole"  # pinhole | opencv | simple_radial (data/demo/lens.py LENSES)

    def __post_init__(self):
        _at_least(self, "data.demo", 2, "views", "width", "height")
        require(self.lens in ("pinhole", "opencv", "simple_radial"), "data.demo.lens", self.lens,
                "must be pinhole, opencv or simple_radial", "e.g. data.demo.lens=opencv")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """``path``: a scene folder — COLMAP (``images/`` and ``sparse/0/``), Blender / NeRF-synthetic
    (``transforms_train.json``) or nerfstudio (``transforms.json``); None = the demo scene.
    ``format``: its layout, ``auto`` = detected by the files present (:mod:`cusgs_jax.data.layouts`).
    ``random_points``: uniform initial points for layouts without SfM points
    (:mod:`cusgs_jax.data.random_points`)."""

    path: Optional[str] = None
    format: str = "auto"  # auto | colmap | blender | nerfstudio
    downscale: int = 1  # 2, 4, 8 read images_2/… when present, else downscale images/
    holdout_every: int = 8  # every 8th image is held out (Mip-NeRF 360); 0 = none
    # The normalised frame (data/normalize.py): "none" keeps the model's axes, "principal" turns them onto the SfM
    # points' principal axes (gsplat's align_principal_axes).
    align: str = "none"
    random_points: int = 100_000  # Blender scenes, nerfstudio scenes without a PLY (3DGS: 100k)
    random_init: str = "auto"  # data/random_points.py: cube (3DGS), cube_and_rays (a room's walls) or by layout
    carve: str = "auto"  # auto: drop random points no training view can hold (frusta, alpha; data/carve.py) | none
    # Distorted cameras: "lens" rasterises through the lens (splat/lens.py), "crop" undistorts to the largest valid
    # rectangle (data/undistort.py, as gsplat), "mask" to the source frame with its invalid pixels left out.
    undistort: str = "lens"
    demo: DemoConfig = dataclasses.field(default_factory=DemoConfig)

    def __post_init__(self):
        _at_least(self, "data", 1, "downscale")
        _at_least(self, "data", 0, "holdout_every")
        require(self.align in ("none", "principal"), "data.align", self.align,
                "must be none (keep the model's axes) or principal (rotate onto the points' principal axes)",
                "e.g. data.align=principal")
        require(self.format in ("auto",) + DATASET_FORMATS, "data.format", self.format,
                f"must be auto or one of {', '.join(DATASET_FORMATS)} (the layout of data.path)",
                "e.g. data.format=auto to detect it from the files present")
        _at_least(self, "data", 2, "random_points")
        require(self.random_init in RANDOM_INITS, "data.random_init", self.random_init,
                "must be auto (by the scene layout), cube (uniform in the cube the cameras look at) or cube_and_rays "
                "(half of the points along the training rays)", "e.g. data.random_init=cube_and_rays")
        require(self.carve in ("auto", "none"), "data.carve", self.carve, "must be auto (carve random initial points "
                "by the training views' frusta and alpha) or none (keep them all)", "e.g. data.carve=none")
        require(self.undistort in CAMERA_FRAMES, "data.undistort", self.undistort,
                "must be crop (keep the largest valid rectangle), mask (keep the frame, mask its invalid pixels) "
                "or lens (keep the images, render through the lens)", "e.g. data.undistort=lens")


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """The run: length, seed, checkpoints, logging."""

    iterations: int = 3000
    seed: int = 0
    resume: bool = False  # continue from the newest checkpoint in checkpoint_dir
    checkpoint_dir: Optional[str] = None  # default: <run folder>/checkpoints
    checkpoint_every: int = 1000
    log_every: int = 10
    progress: bool = True
    # Views per step (gsplat's batch_size): the loss is their mean, the densification statistics add every view,
    # learning rates follow training/optim.py::batch_scaled (√B, Adam β^B).
    batch_size: int = 1
    # Local devices the B views are sharded over (training/parallel.py): "auto" = the most that divide B.
    devices: str = "auto"
    viewer: bool = False  # serve a live web viewer of the model while training (cusgs_jax/view/live.py)
    viewer_port: int = 8080  # 0: a free port (the address is logged)
    viewer_budget: float = 0.1  # at most this share of the training wall time goes to rendering the live view
    compilation_cache: Optional[str] = "auto"  # persistent XLA cache: auto, a folder or None (app/xla_cache.py)
    compile_ahead: bool = True  # compile the programs the loop will need on a background thread (app/ahead.py)
    # A view whose grown program is still compiling waits while the loop trains the views that fit (app/deferral.py);
    # false: the loop waits for it, and a run's numbers never depend on when a background compile finished.
    defer_views: bool = True

    def __post_init__(self):
        require(_number(self.iterations) and self.iterations >= 1, "train.iterations", self.iterations,
                "must be a whole number of steps >= 1", "e.g. train.iterations=30000")
        _at_least(self, "train", 0, "checkpoint_every")
        _at_least(self, "train", 1, "log_every")
        require(isinstance(self.batch_size, int) and not isinstance(self.batch_size, bool) and self.batch_size >= 1,
                "train.batch_size", self.batch_size, "must be a whole number of views per step >= 1",
                "e.g. train.batch_size=2")
        devices = str(self.devices)
        require(devices == "auto" or (devices.isdigit() and int(devices) >= 1), "train.devices", self.devices,
                "must be auto or a whole number of devices >= 1", "e.g. train.devices=auto")
        require(devices == "auto" or self.batch_size % int(devices) == 0, "train.devices", self.devices,
                f"must divide train.batch_size={self.batch_size} (each device renders B/devices views)",
                f"use train.devices=auto or a batch size that is a multiple of {devices}")
        require(_number(self.viewer_port) and 0 <= self.viewer_port <= 65535, "train.viewer_port", self.viewer_port,
                "must be a port number 0-65535 (0: a free one)")
        require(_number(self.viewer_budget) and 0 < self.viewer_budget <= 1, "train.viewer_budget",
                self.viewer_budget, "must be a share of the training time in (0, 1]", "e.g. train.viewer_budget=0.1")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    every: int = 250  # held-out PSNR for the error-against-time curve
    save_renders: bool = True

    def __post_init__(self):
        _at_least(self, "eval", 0, "every")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Scaffold-GS anchors (docs/method.md#scaffold-anchors).

    Lengths are in units of the scene extent: every run trains in the normalised
    world frame of :mod:`cusgs_jax.data.normalize` (camera extent 1), so a
    setting means the same for a COLMAP model at any scale. ``voxel_size``:
    the cell ``l`` as a fraction of the extent, or None (``model.voxel_size=auto``
    in YAML and on the command line), Scaffold-GS's rule for ``voxel_size <= 0``:
    the median spacing of the SfM points (:func:`cusgs_jax.model.anchors.auto_voxel_size`;
    for random initial points :func:`cusgs_jax.data.random_points.random_voxel_size`),
    resolved in setup by :func:`cusgs_jax.app.resolve.resolve_voxel_size`.
    """

    voxel_size: Optional[float] = None  # None: auto
    n_offsets: int = 10
    latent_dim: int = 32
    hidden: int = 32
    appearance: bool = True
    appearance_dim: int = 32
    capacity_factor: float = 2.0
    # Anchor capacities on one ladder (model/anchors.py::capacity_rung, four rungs per doubling): jobs of a voxel-size
    # sweep whose anchor counts fall on one rung share programs; a single run pays up to 25 % more slots for it.
    capacity_ladder: bool = False
    frustum_margin: float = 0.15
    # Frustum anchors are gathered into ceil(visible_fraction · A) slots before decoding (culled ones cost nothing);
    # a first guess: a view that sees more grows it and the step replays (training/capacity.py). 1.0: every slot.
    visible_fraction: float = 0.6
    # feature queries: "per_anchor" (hierarchical q_v → q_{v,n}) or "per_gaussian" (ablation)
    query_granularity: str = "per_anchor"
    # The networks' matmuls (precision.py): "highest" = the same numbers on every backend; "default" = the backend's
    # (TF32 on NVIDIA GPUs since Ampere). Geometry is at full float32 whatever this says.
    matmul_precision: str = "highest"

    def __post_init__(self):
        require(self.voxel_size is None or (_number(self.voxel_size) and self.voxel_size > 0), "model.voxel_size",
                self.voxel_size, "must be None (auto; 'auto' is only the YAML / command-line spelling) or a cell "
                "size > 0 in units of the scene extent", "in Python write voxel_size=None or e.g. voxel_size=0.01")
        if self.voxel_size is not None:
            object.__setattr__(self, "voxel_size", float(self.voxel_size))
        _at_least(self, "model", 1, "n_offsets", "latent_dim", "hidden", "capacity_factor")
        _at_least(self, "model", 0, "appearance_dim", "frustum_margin")
        require(isinstance(self.capacity_ladder, bool), "model.capacity_ladder", self.capacity_ladder,
                "must be true or false")
        require(_number(self.visible_fraction) and 0 < self.visible_fraction <= 1, "model.visible_fraction",
                self.visible_fraction, "must lie in (0, 1] (it only sets the first visible-slot capacity, "
                "which grows when a view sees more)")
        require(self.query_granularity in QUERY_GRANULARITIES, "model.query_granularity", self.query_granularity,
                f"must be one of {QUERY_GRANULARITIES}")
        require(self.matmul_precision in MATMUL_PRECISIONS, "model.matmul_precision", self.matmul_precision,
                f"must be one of {MATMUL_PRECISIONS}", "e.g. model.matmul_precision=highest")

    def decoder(self) -> DecoderConfig:
        return DecoderConfig(self.n_offsets, self.latent_dim, self.hidden,
                             self.appearance_dim if self.appearance else 0, self.matmul_precision)


@dataclasses.dataclass(frozen=True)
class DecoderConfig:
    """Static decoder shape (closed over, never traced); usually ``ModelConfig.decoder()``."""

    n_offsets: int = ModelConfig.n_offsets
    latent_dim: int = ModelConfig.latent_dim
    hidden: int = ModelConfig.hidden
    appearance_dim: int = ModelConfig.appearance_dim  # 0 disables the appearance embedding
    matmul_precision: str = ModelConfig.matmul_precision  # of the heads' matmuls (cusgs_jax/precision.py)


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    """Rasteriser settings (the image does not depend on tile/chunk size; 8/16 is fastest on CPU)."""

    tile_size: int = 8
    chunk_size: int = 16
    # First guesses of two work capacities (training/capacity.py: grown, and the step replayed, when a view needs
    # more): the share of the S·N decoded Gaussians reaching the splatter (model/active.py), tile pairs per such one.
    active_fraction: float = 0.375
    max_pairs_per_gaussian: float = 6.0
    antialiased: bool = False
    backend: str = "auto"  # the compositor: auto = Pallas kernels on a GPU, JAX elsewhere (splat/render.py)
    tiles: str = "box"  # tiles a Gaussian is binned into: box (its whole box) | ellipse (only where α ≥ 1/255 reaches)
    # RGB in [0, 1] behind the Gaussians and under images with alpha. None: the layout's (white for Blender, else
    # black: data/finish.py); a run records the colour it used (training/inputs.py). Renderers read background_color.
    background: Optional[tuple[float, float, float]] = None

    def __post_init__(self):
        _tuples(self)
        _at_least(self, "splat", 1, "tile_size", "chunk_size")
        require(self.backend in COMPOSITORS, "splat.backend", self.backend, f"must be one of {', '.join(COMPOSITORS)}")
        require(self.tiles in ("box", "ellipse"), "splat.tiles", self.tiles,
                "must be box (every tile of a Gaussian's box) or ellipse (only the tiles its α >= 1/255 ellipse "
                "reaches: fewer pairs, gradients equal to rounding)", "e.g. splat.tiles=ellipse")
        require(self.backend != "pallas" or self.tile_size & (self.tile_size - 1) == 0, "splat.tile_size",
                self.tile_size, "must be a power of two with splat.backend=pallas (the kernels' blocks)",
                "e.g. splat.tile_size=8 or 16")
        require(_number(self.max_pairs_per_gaussian) and self.max_pairs_per_gaussian > 0,
                "splat.max_pairs_per_gaussian", self.max_pairs_per_gaussian, "must be > 0")
        require(_number(self.active_fraction) and 0 < self.active_fraction <= 1, "splat.active_fraction",
                self.active_fraction, "must lie in (0, 1] (it only sets the first active-Gaussian capacity, "
                "which grows when a view has more)")
        require(self.background is None
                or (len(self.background) == 3 and all(_number(c) and 0 <= c <= 1 for c in self.background)),
                "splat.background", self.background, "must be three numbers in [0, 1] (or null: the dataset's "
                "default, white for Blender scenes and black otherwise)", "e.g. splat.background=[1,1,1]")

    @property
    def background_color(self) -> tuple[float, float, float]:
        """``background``, or black when it is not set (None) and no scene has resolved it."""
        return (0.0, 0.0, 0.0) if self.background is None else tuple(float(c) for c in self.background)


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """``L_img = l1·L1 + ssim·(1 − SSIM) + volume·mean(prod(scale))`` (Scaffold-GS)."""

    l1_weight: float = 0.8
    ssim_weight: float = 0.2
    volume_weight: float = 0.01  # mean(prod(scale)) in units of the scene extent (data/normalize.py)

    def __post_init__(self):
        _at_least(self, "loss", 0, "l1_weight", "ssim_weight", "volume_weight")


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """(initial, final) learning rate per parameter group; decay is log-linear over the run.

    ``offsets`` is multiplied by the scene extent (Scaffold-GS ``spatial_lr_scale``).
    """

    offsets: tuple[float, float] = (0.01, 0.0001)
    latent: tuple[float, float] = (0.0075, 0.0075)
    scaling: tuple[float, float] = (0.007, 0.007)
    mlp_opacity: tuple[float, float] = (0.002, 0.00002)
    mlp_cov: tuple[float, float] = (0.004, 0.004)
    mlp_color: tuple[float, float] = (0.008, 0.00005)
    appearance: tuple[float, float] = (0.05, 0.0005)
    features: tuple[float, float] = (0.0005, 0.0005)  # query and memory heads (M3 f_emb)
    eps: float = 1e-15
    # Row-sparse update (gsplat's "visible Adam"): with one view per step only the decoded anchors' rows of the
    # parameters and Adam moments are updated (unseen moments stay). false: dense Adam over every alive row.
    sparse: bool = True

    def __post_init__(self):
        _tuples(self)
        for group, rates in self.groups().items():
            _require_rates(f"optim.{group}", rates)
        require(_number(self.eps) and self.eps > 0, "optim.eps", self.eps, "must be a number > 0 (Adam's epsilon)",
                "e.g. optim.eps=1e-15")
        require(isinstance(self.sparse, bool), "optim.sparse", self.sparse, "must be true or false")

    def groups(self) -> dict[str, tuple[float, float]]:
        """{group: (initial, final)} for every learning-rate group."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("eps", "sparse")}


def _require_rates(option: str, rates) -> None:
    """An ``optim.<group>`` setting: (initial, final) learning rates, finite and >= 0; a decaying pair (initial !=
    final) > 0 both, since the decay is log-linear (training/optim.py::log_linear_schedule)."""
    pair = isinstance(rates, tuple) and len(rates) == 2
    example = f"e.g. {option}=[{OptimConfig.offsets[0]},{OptimConfig.offsets[1]}] (initial, final), or the same " \
              "number twice for a constant rate"
    require(pair and all(_number(rate) and rate >= 0 for rate in rates), option,
            list(rates) if isinstance(rates, tuple) else rates,
            "must be two finite learning rates >= 0, (initial, final)", example)
    require(rates[0] == rates[1] or min(rates) > 0, option, list(rates),
            "a decaying rate (initial != final) must be > 0 at both ends: the decay is log-linear", example)


@dataclasses.dataclass(frozen=True)
class GrowConfig:
    """Scaffold-GS densification schedule and thresholds.

    The step schedule is compressed for the 3000-step default run;
    ``grow=scaffold`` (conf/grow/scaffold.yaml) is Scaffold-GS's 30k schedule.
    """

    stats_start: int = 100  # accumulate statistics from this step
    start: int = 400  # first growing/pruning step
    stop: int = 1500  # last growing/pruning step
    interval: int = 100
    grad_threshold: float = 0.0002
    min_opacity: float = 0.005
    success_threshold: float = 0.8
    levels: int = 3  # update_depth
    init_factor: int = 16  # update_init_factor
    hierarchy_factor: int = 4  # update_hierachy_factor
    capacity_growth: float = 1.5
    # Random starts (no points): Scaffold-GS's opacity prune every early_cull_every steps before `start`
    # (densify/early_cull.py); auto = on for random starts not carved by alpha, off otherwise.
    early_cull: str = "auto"  # auto | on | off
    early_cull_every: int = 50

    def __post_init__(self):
        _at_least(self, "grow", 1, "interval", "levels", "init_factor", "hierarchy_factor", "early_cull_every")
        require(self.early_cull in ("auto", "on", "off"), "grow.early_cull", self.early_cull,
                "must be auto (on for random starts not carved by alpha), on or off", "e.g. grow.early_cull=off")
        require(_number(self.capacity_growth) and self.capacity_growth > 1, "grow.capacity_growth",
                self.capacity_growth, "must be > 1")


@dataclasses.dataclass(frozen=True)
class PruneConfig:
    """Feature-aware pruning schedule and weights (paper defaults; densify/feature_prune.py).

    Attributes:
      strategy: "feature_aware" | "scaffold" | "none" ("scaffold" and "none" keep only
        Scaffold-GS's opacity pruning, which runs with growing).
      ratio: fraction of the alive anchors removed per pass (0.1 %).
      interval, start, stop: a pass at every step ``s`` with
        ``start ≤ s ≤ stop`` and ``s % interval == 0``.
      lambda_norm, lambda_grad: λ_n, λ_g.
      volume_power: LightGaussian's exponent in ``(V / V_ref)^power``.
      volume_percentile: V_ref is the entry at ``floor(p/100 · G)`` of the
        active volumes sorted in decreasing order (LightGaussian's "90th
        largest percentile", i.e. a small volume).
      min_visits: anchors decoded in fewer views since the last pass are not
        pruned (0: every alive anchor is a candidate).
    """

    strategy: str = "feature_aware"
    ratio: float = 0.001
    interval: int = 100
    start: int = 500
    stop: int = 15000
    lambda_norm: float = 2.0
    lambda_grad: float = 8.0
    volume_power: float = 0.1
    volume_percentile: float = 90.0
    min_visits: int = 1

    def __post_init__(self):
        require(self.strategy in PRUNE_STRATEGIES, "prune.strategy", self.strategy,
                f"must be one of {PRUNE_STRATEGIES}")
        require(_number(self.ratio) and 0.0 <= self.ratio < 1.0, "prune.ratio", self.ratio,
                "is the fraction of alive anchors removed per pass and must lie in [0, 1) (1 would remove "
                "every anchor)", "the paper uses prune.ratio=0.001; prune.ratio=0 or prune=none disables it")
        require(_number(self.volume_percentile) and 0.0 <= self.volume_percentile <= 100.0,
                "prune.volume_percentile", self.volume_percentile, "must lie in [0, 100]")
        _at_least(self, "prune", 1, "interval")
        _at_least(self, "prune", 0, "lambda_norm", "lambda_grad", "min_visits")


@dataclasses.dataclass(frozen=True)
class FeatureModelConfig:
    """One foundation model's slice of the field (``query_dim`` 0 = M3's split, else 16). ``required`` false:
    left out, with a warning, when its extractor's optional package is missing (:mod:`cusgs_jax.extract.optional`)."""

    name: str = "?"
    query_dim: int = 0
    gamma: float = 0.8  # PSC cosine threshold
    adapter: str = "affine"
    required: bool = True

    def __post_init__(self):
        require(isinstance(self.required, bool), f"features.models[{self.name}].required", self.required,
                "must be true or false")
        if self.query_dim <= 0:
            object.__setattr__(self, "query_dim", M3_QUERY_DIMS.get(self.name, 16))


# The demo scene's stand-in "foundation models" (features=auto on the demo scene, features=demo):
# DAISY descriptors (104-D), the generator's per-object vectors (32-D) and ImageNet VGG16 relu3_3
# (256-D at 1/4 resolution; PSC bank of about 840 entries at gamma 0.45, extract/vgg.py says why).
# vgg16 is not required: setup leaves it out without the lpips extra (its weights), so the demo trains anyway.
DEMO_FEATURE_MODELS = (FeatureModelConfig("daisy", 16, 0.8), FeatureModelConfig("semantic", 16, 1.0),
                       FeatureModelConfig("vgg16", 16, 0.45, required=False))


@dataclasses.dataclass(frozen=True)
class FeatureConfig:
    """Multimodal feature field (closed over, never traced).

    ``models``: a tuple of :class:`FeatureModelConfig`, or None ("auto"): the demo's
    models (:data:`DEMO_FEATURE_MODELS`) on the built-in demo scene and none on a user's
    scene, resolved by :meth:`resolve` in setup (unresolved it means none). In YAML and on the
    command line: ``auto``, ``demo`` or a list of ``{name: …, query_dim: …}`` (:func:`cusgs_jax.compose.from_dict`
    converts them).
    """

    models: Optional[tuple[FeatureModelConfig, ...]] = None  # None: auto
    hidden: int = 32
    weight: float = 0.5  # λ_e (M3)
    sample_pixels: int = 2000  # pixels per step for the feature loss; 0 = all
    sparse_queries: bool = True  # the train step composites the queries only at the pixels the loss can read
    max_bank_entries: int = 1024  # PSC cap per model (rows are scanned in a seeded random order)
    psc_rows: int = 200_000  # training pixels (seeded random subset) the PSC scan looks at
    auto_extract: bool = True  # extract missing built-in features (daisy, hog, gabor, semantic, vgg16)

    def __post_init__(self):
        _tuples(self)
        models = self.models
        require(models is None or (isinstance(models, tuple)
                                   and all(isinstance(m, FeatureModelConfig) for m in models)),
                "features.models", models, "must be None (auto) or a tuple of FeatureModelConfig",
                "'auto', 'demo' and lists of dicts are the YAML / command-line spellings, which from_dict "
                "converts; in Python write e.g. models=(FeatureModelConfig('daisy'),) or DEMO_FEATURE_MODELS")

    def resolve(self, demo_scene: bool) -> FeatureConfig:
        """``models=None`` (auto) → :data:`DEMO_FEATURE_MODELS` on the demo scene, else none; set models stay.
        Pure: setup then leaves out models whose package is missing (:mod:`cusgs_jax.extract.optional`)."""
        if self.models is not None:
            return self
        return dataclasses.replace(self, models=DEMO_FEATURE_MODELS if demo_scene else ())

    @property
    def model_list(self) -> tuple[FeatureModelConfig, ...]:
        """The models; none while ``models`` is None (auto, unresolved)."""
        return self.models or ()

    @property
    def enabled(self) -> bool:
        return bool(self.model_list)

    @property
    def query_dim(self) -> int:
        return sum(m.query_dim for m in self.model_list)

    def slices(self) -> list[tuple[str, slice]]:
        """(model name, channel slice of the query) in order."""
        out, start = [], 0
        for m in self.model_list:
            out.append((m.name, slice(start, start + m.query_dim)))
            start += m.query_dim
        return out


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything a run depends on; the step factories close over it (static)."""

    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    train: TrainOptions = dataclasses.field(default_factory=TrainOptions)
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)
    model: ModelConfig = dataclasses.field(default_factory=ModelConfig)
    splat: SplatConfig = dataclasses.field(default_factory=SplatConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    grow: GrowConfig = dataclasses.field(default_factory=GrowConfig)
    features: FeatureConfig = dataclasses.field(default_factory=FeatureConfig)
    prune: PruneConfig = dataclasses.field(default_factory=PruneConfig)

    def replace(self, **groups) -> Config:
        """``cfg.replace(model=dict(voxel_size=0.1), train=dict(iterations=50))``: nested partial update (a dict
        for a group updates its fields, ``data=dict(demo=dict(views=9))`` nested ones). A name that is no field,
        at any level, raises :class:`~cusgs_jax.errors.ConfigError` naming the nearest option
        (:func:`unknown_option`)."""
        return _replaced(self, groups, "")


def _replaced(obj, changes: dict, prefix: str):
    """``dataclasses.replace(obj, **changes)``, dict values of dataclass fields replaced into them recursively."""
    names = [f.name for f in dataclasses.fields(obj)]
    new = {}
    for name, value in changes.items():
        if name not in names:
            raise unknown_option(prefix + name, value)
        current = getattr(obj, name)
        if isinstance(value, dict) and dataclasses.is_dataclass(current):
            value = _replaced(current, value, f"{prefix}{name}.")
        new[name] = value
    return dataclasses.replace(obj, **new)


def _option_groups(cls: type = Config, prefix: str = "") -> dict[str, list[str]]:
    """{group ("" for the top level, "train", "data.demo"): its field names}."""
    hints = {f.name: f.default_factory for f in dataclasses.fields(cls)}
    groups = {prefix.rstrip("."): list(hints)}
    for name, factory in hints.items():
        if isinstance(factory, type) and dataclasses.is_dataclass(factory):
            groups.update(_option_groups(factory, f"{prefix}{name}."))
    return groups


def option_names() -> list[str]:
    """Every option's dotted name, as overrides write it: ``data.path``, …, ``data.demo.views``, …,
    ``prune.min_visits``."""
    groups = _option_groups()
    dotted = (f"{group}.{name}" if group else name for group, names in groups.items() for name in names)
    return [option for option in dotted if option not in groups]


def unknown_option(option: str, value=dataclasses.MISSING, shown: Optional[str] = None) -> ConfigError:
    """The :class:`~cusgs_jax.errors.ConfigError` for ``option`` (dotted, e.g. ``train.iteration``) that is no
    field of :class:`Config`: it names the nearest option (:mod:`difflib`) and the options of its group.
    ``value`` is shown as its repr, ``shown`` as it is (a command line's text)."""
    groups = _option_groups()
    group, _, leaf = option.rpartition(".")
    siblings = groups.get(group)
    options = option_names() + ([g for g in groups if g] if not group else [])  # a group for a top-level name
    nearest = [o for o in options if o.rpartition(".")[2] == leaf]  # the right name in another group
    close = difflib.get_close_matches(leaf, siblings or [], 1, 0.6)
    nearest = nearest or [f"{group}.{n}" if group else n for n in close]
    nearest = nearest or difflib.get_close_matches(option, options, 1, 0.6)
    text = shown if shown is not None else ("" if value is dataclasses.MISSING else repr(value))
    where = (f"{group} holds {', '.join(siblings)}" if group else f"the groups are {', '.join(siblings)}") \
        if siblings is not None else f"the groups are {', '.join(groups[''])}"
    hint = f"did you mean {nearest[0]}? ({where})" if nearest else where
    return ConfigError(f"{option}{'=' + text if text else ''}: no such option; {hint}")
