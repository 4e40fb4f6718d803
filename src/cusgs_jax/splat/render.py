"""Public rasterisation API: project → bin into tiles → composite.

Naming: G Gaussians, C channels, H×W image, B cameras.
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import COMPOSITORS
from cusgs_jax.splat.composite import composite_tiles, default_lanes
from cusgs_jax.splat.composite_pallas import DEFAULT_BATCH as PALLAS_BATCH, composite_tiles_pallas
from cusgs_jax.splat.lens import Lens
from cusgs_jax.splat.project import project_gaussians
from cusgs_jax.splat.tiles import TileGrid, intersect_tiles

log = logging.getLogger("cusgs_jax")


class RenderOutput(NamedTuple):
    """Everything a render returns (a pytree of arrays).

    Attributes:
      image: [H, W, C] Σ c α T + T_final · background.
      alpha: [H, W] 1 − T_final.
      depth: [H, W] Σ z α T (alpha-weighted camera depth, not normalised).
      n_contrib: [H, W] int32 Gaussians composited per pixel.
      means2d: [G, 2] projected centres (differentiable; densification uses
        its gradient).
      radii: [G, 2] int32 footprint half-extents in pixels (0 = culled),
        clamped to 2^30.
      visible: [G] bool.
      significance: [G] Σ over composited pixels of opacity·T (LightGaussian;
        the compositing opacity, i.e. compensated in antialiased mode).
        Not differentiable.
      hits: [G] int32 pixels each Gaussian was composited into.
      overflow: [] int32 tile–Gaussian pairs dropped because ``max_pairs``
        was exceeded (0 means the image is exact).
      num_pairs: [] int32 tile–Gaussian pairs composited.
    """

    image: jax.Array
    alpha: jax.Array
    depth: jax.Array
    n_contrib: jax.Array
    means2d: jax.Array
    radii: jax.Array
    visible: jax.Array
    significance: jax.Array
    hits: jax.Array
    overflow: jax.Array
    num_pairs: jax.Array


class Compositor(NamedTuple):
    """How the tiles are composited: tuning that changes the speed, never the image (beyond rounding).

    Attributes:
      backend: ``"jax"`` (lanes of chunks, any backend), ``"pallas"`` (:mod:`~cusgs_jax.splat.composite_pallas`:
        Triton kernels on a GPU, Pallas's interpreter elsewhere — exact but slow, for tests) or ``"auto"``
        (:func:`resolve_backend`); ``splat.backend``.
      chunk_size: the JAX compositor's Gaussians per tile per compositing step (``splat.chunk_size``).
      lanes: the JAX compositor's tiles composited side by side (a lane that finishes its tile takes the next
        one); None: :func:`~cusgs_jax.splat.composite.default_lanes`.
      tiles: which tiles a Gaussian is binned into (``splat.tiles``): ``"box"``, every tile of its opacity-aware
        box (the default), or ``"ellipse"``, only the tiles its α ≥ 1/255 ellipse reaches
        (:func:`~cusgs_jax.splat.tiles.footprint_rows`: about 0.74× the pairs, forward+backward 10–20 % faster on
        a CPU; images the same, gradients to float rounding — the scatter-add order follows the slots).

    The Pallas kernels have their own blocks and ignore ``chunk_size`` and ``lanes``.
    """

    backend: str = "auto"
    chunk_size: int = 16
    lanes: int | None = None
    tiles: str = "box"


class SparseChannels(NamedTuple):
    """The last ``count`` colour channels composited only at some pixels (static, hashable).

    A loss that reads a few pixels of some channels — the feature loss reads each feature map's pixel
    centres only — needs those channels nowhere else; the JAX compositor then evaluates them at each
    tile's listed pixels (K of S), not at all S. Elsewhere the image holds 0 in those channels (the
    background is added at the listed pixels only). The Pallas compositor composites them everywhere and
    the same zeros are applied, so both give the same image.

    Attributes:
      count: Q, the number of trailing channels of ``colors`` this applies to (≥ 1).
      pixels: the flat pixel indices ``row · width + column`` where they are composited, distinct.
    """

    count: int
    pixels: tuple[int, ...]

    def slots(self, grid: TileGrid) -> tuple[np.ndarray, np.ndarray]:
        """([T, K] int32 pixel index within each tile, S where unused; [T, K] int32 flat image pixel, H·W where
        unused), K = the most listed pixels in one tile (at least 1)."""
        flat = np.unique(np.asarray(self.pixels, np.int64))
        if flat.size and (flat.min() < 0 or flat.max() >= grid.width * grid.height):
            raise ValueError(f"SparseChannels.pixels must lie in [0, {grid.width * grid.height}) for a "
                             f"{grid.width}x{grid.height} image, got {flat.min()}..{flat.max()}")
        row, col = np.divmod(flat, grid.width)
        ts = grid.tile_size
        tile = (row // ts) * grid.tiles_x + col // ts
        within = (row % ts) * ts + col % ts
        k = max(1, int(np.bincount(tile, minlength=grid.num_tiles).max()))
        order = np.argsort(tile, kind="stable")
        tile, within, flat = tile[order], within[order], flat[order]
        rank = np.arange(flat.size) - np.searchsorted(tile, tile, side="left")
        slots = np.full((grid.num_tiles, k), ts * ts, np.int32)
        image = np.full((grid.num_tiles, k), grid.width * grid.height, np.int32)
        slots[tile, rank] = within
        image[tile, rank] = flat
        return slots, image


def default_max_pairs(num_gaussians: int, width: int, height: int, tile_size: int = 16) -> int:
    """Default tile–Gaussian pair capacity.

    ``ceil(8 · (16 / tile_size)^1.5)`` pairs per Gaussian (8 at tile 16, 23 at
    tile 8) plus 64 per tile: about twice what footprints of 3–30 pixels need.
    Larger footprints may overflow; ``RenderOutput.overflow`` says so.
    """
    grid = TileGrid(width, height, tile_size)
    per_gaussian = math.ceil(8 * (16 / tile_size) ** 1.5)
    return int(per_gaussian * num_gaussians + 64 * grid.num_tiles)


def resolve_backend(backend: str, platform: str | None = None) -> str:
    """The compositor ``rasterize(backend=...)`` runs: ``"jax"`` or ``"pallas"``.

    ``"auto"`` is the Pallas kernels on a GPU, where ``benchmarks/gpu_check.py`` measured them
    faster with their tests passing there, and the pure-JAX compositor on every other backend,
    where Pallas only interprets (docs/benchmarks.md#on-a-gpu).

    Args:
      backend: ``"auto"``, ``"jax"`` or ``"pallas"``.
      platform: the backend that runs the render (default: ``jax.default_backend()``).
    """
    if backend not in COMPOSITORS:
        raise ValueError(f"backend must be one of {COMPOSITORS}, got {backend!r}")
    platform = platform or jax.default_backend()
    if backend == "auto":
        return "pallas" if platform == "gpu" and pallas_gpu_available() else "jax"
    if backend == "pallas" and platform != "gpu":
        _interpreting(platform)
    return backend


@functools.cache
def _interpreting(platform: str) -> None:
    """Say once that ``backend="pallas"`` off a GPU runs Pallas's interpreter."""
    log.warning("splat.backend=pallas on %s runs the Pallas kernels in Pallas's interpreter: exact but about 10-100x "
                "slower than splat.backend=jax (meant for tests); use splat.backend=auto or jax there", platform)


@functools.cache
def pallas_gpu_available() -> bool:
    """Whether this JAX still has Pallas's Triton backend, which the GPU kernels lower through
    (:mod:`cusgs_jax.splat.composite_pallas`; deprecated since JAX 0.11, "will be removed in a future
    version"). When it is gone, ``auto`` says so once and composites with the JAX compositor."""
    try:
        from jax.experimental.pallas import triton as pl_triton
    except ImportError as error:
        log.warning("splat.backend=auto: this JAX has no Pallas Triton backend (%s); the JAX compositor runs "
                    "instead of the Pallas kernels (slower on a GPU, the same numbers)", error)
        return False
    if getattr(pl_triton, "CompilerParams", None) is None and getattr(pl_triton, "TritonCompilerParams", None) is None:
        log.warning("splat.backend=auto: this JAX's Pallas Triton backend has no compiler parameters; the JAX "
                    "compositor runs instead of the Pallas kernels (slower on a GPU, the same numbers)")
        return False
    return True


def _tiles_to_image(tiles: jax.Array, grid: TileGrid) -> jax.Array:
    """[T, S, ...] per-tile pixels → [H, W, ...] image (padding cropped)."""
    ts = grid.tile_size
    rest = tiles.shape[2:]
    img = tiles.reshape(grid.tiles_y, grid.tiles_x, ts, ts, *rest)
    img = jnp.moveaxis(img, 2, 1).reshape(grid.tiles_y * ts, grid.tiles_x * ts, *rest)
    return img[: grid.height, : grid.width]


RASTERIZE_STATIC_ARGNAMES = (
    "width", "height", "near", "far", "antialiased", "eps2d", "tile_size", "max_pairs", "compositor",
    "sparse_channels", "validate",
)
"""The arguments of :func:`rasterize` and :func:`rasterize_batch` that must be static under ``jax.jit``:
``jax.jit(rasterize, static_argnames=RASTERIZE_STATIC_ARGNAMES)`` is :data:`rasterize_jit`."""

# Keywords rasterize() once took, and what replaced them (a caller still passing one gets a TypeError saying so).
_REMOVED_KEYWORDS = {
    "backend": "compositor=Compositor(backend=...)",
    "chunk_size": "compositor=Compositor(chunk_size=...)",
    "lanes": "compositor=Compositor(lanes=...)",
}


def _refuse_keywords(function: str, keywords: dict) -> None:
    """TypeError for keywords :func:`rasterize` does not take, naming the replacement of a removed one."""
    for name in keywords:
        if name in _REMOVED_KEYWORDS:
            raise TypeError(f"{function}() no longer takes {name}=; pass {_REMOVED_KEYWORDS[name]} instead "
                            "(cusgs_jax.splat.Compositor: backend, chunk_size, lanes)")
        raise TypeError(f"{function}() got an unexpected keyword argument {name!r}")


def _is_traced(*values) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(values))


def _as_array(value):
    """A NumPy or JAX array (or tracer) as it is; anything else (a list, a tuple, a scalar) through jnp.asarray."""
    if value is None or isinstance(value, (np.ndarray, jax.Array, jax.core.Tracer)):
        return value
    return jnp.asarray(value)


def _require_static(function: str, **values) -> None:
    """TypeError when a static argument arrives traced (``jax.jit(rasterize)`` without ``static_argnames``)."""
    for name, value in values.items():
        if _is_traced(value):
            raise TypeError(f"{function}(): {name} is a traced value, but {name} must be static (it fixes the shapes "
                            "or the program): jit with cusgs_jax.splat.rasterize_jit / rasterize_batch_jit, or "
                            "jax.jit(f, static_argnames=cusgs_jax.splat.RASTERIZE_STATIC_ARGNAMES)")


def rasterize(
    means: jax.Array,
    quats: jax.Array,
    scales: jax.Array,
    opacities: jax.Array,
    colors: jax.Array,
    viewmat: jax.Array,
    K: jax.Array,
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: jax.Array | None = None,
    antialiased: bool = False,
    eps2d: float = 0.3,
    tile_size: int = 16,
    max_pairs: int | None = None,
    means2d_delta: jax.Array | None = None,
    lens: Lens | None = None,
    compositor: Compositor = Compositor(),
    sparse_channels: SparseChannels | None = None,
    validate: bool = True,
    **removed,
) -> RenderOutput:
    """Render 3D Gaussians with gsplat 1.5.3's conventions (docs/rasterizer.md).

    Called on concrete arrays it checks them, then runs one jitted program per static configuration (new
    values, same shapes: no recompile). Inside your own ``jax.jit`` the static arguments must be static::

        fast = jax.jit(rasterize, static_argnames=cusgs_jax.splat.RASTERIZE_STATIC_ARGNAMES)
        # = cusgs_jax.splat.rasterize_jit; RASTERIZE_STATIC_ARGNAMES is
        # ("width", "height", "near", "far", "antialiased", "eps2d", "tile_size", "max_pairs", "compositor",
        #  "sparse_channels", "validate")

    Input checks: outside jit (no argument is a tracer) the inputs are checked before rendering —
    shapes and dtypes (:func:`check_shapes`), finite values, ``scales ≥ 0``, ``opacities`` in [0, 1] — and a
    bad one is a ValueError naming the argument (one pass over the arrays; on a device, one transfer of a few
    reductions). Under ``jax.jit``, ``jax.grad`` or ``jax.vmap`` only shapes and static arguments are
    checked (the values are traced): call :func:`check_inputs` on the concrete inputs first, or use
    ``jax.experimental.checkify`` — ``checkify.check(jnp.all(opacities <= 1), "...")`` in your function, and
    ``jax.jit(checkify.checkify(f, errors=checkify.user_checks | checkify.float_checks))`` reports a failed check
    or the first NaN an operation produces (docs/rasterizer.md#calling-it-from-research-code).

    Args:
      means: [G, 3] world centres (a list or tuple is converted with ``jnp.asarray``; so are the other arrays).
      quats: [G, 4] wxyz rotations, need not be normalised.
      scales: [G, 3] linear standard deviations (≥ 0).
      opacities: [G] in [0, 1].
      colors: [G, C] any C ≥ 1 (RGB and feature channels in one pass).
      viewmat: [4, 4] world→camera, OpenCV axes (+z forward, +y down).
      K: [3, 3] pinhole intrinsics.
      width, height: static image size.
      near, far: depth culling planes (static).
      background: [C] or None (black).
      antialiased: gsplat's "antialiased" mode (opacity compensation).
      eps2d: low-pass variance added to every 2D covariance.
      tile_size: static tile edge in pixels (16 as gsplat; 8 is 1.3–1.7x
        faster on CPU, see benchmarks/splat_bench.py). The image does not
        depend on it.
      max_pairs: static tile–Gaussian pair capacity, a positive int; ``None`` uses
        :func:`default_max_pairs`. Exceeding it drops the farthest pairs and is
        reported in ``overflow``.
      means2d_delta: [G, 2] or None, added to the projected centres. Pass
        zeros and differentiate with respect to it to get ∂L/∂μ_2D (the
        screen-space gradient densification statistics use).
      lens: the camera's lens distortion (:class:`~cusgs_jax.splat.lens.Lens`, one camera), or
        None for a pinhole camera; the image is then the distorted camera's picture.
      compositor: static; how the tiles are composited (:class:`Compositor`: backend, the JAX compositor's
        chunk size and lanes; the former ``backend=``, ``chunk_size=`` and ``lanes=`` keywords). Projection,
        sorting and binning are the same for all; the image agrees to rounding.
      sparse_channels: static; the last Q channels composited only at the pixels it lists
        (:class:`SparseChannels`; 0 elsewhere), or None (every channel everywhere).
      validate: static; False skips the value checks outside jit (shapes are always checked).
    Returns:
      :class:`RenderOutput`. Differentiable with respect to means, quats,
      scales, opacities, colors, background (and viewmat, K).
    Raises:
      ValueError: a wrong shape, dtype, size or ``max_pairs``, or (outside jit) a non-finite value, a negative
        scale or an opacity outside [0, 1], naming the argument.
      TypeError: a traced static argument (jit without ``static_argnames``) or a removed keyword.
    """
    _refuse_keywords("rasterize", removed)
    _require_static("rasterize", width=width, height=height, tile_size=tile_size, max_pairs=max_pairs, near=near,
                    far=far, eps2d=eps2d, antialiased=antialiased, compositor=compositor,
                    sparse_channels=sparse_channels, validate=validate)
    means, quats, scales, opacities, colors, viewmat, K, background, means2d_delta = (
        _as_array(a) for a in (means, quats, scales, opacities, colors, viewmat, K, background, means2d_delta))
    if validate and not _is_traced(means, quats, scales, opacities, colors, viewmat, K, background, means2d_delta,
                                   lens):
        check_shapes(means, quats, scales, opacities, colors, viewmat, K, width, height, background=background,
                     tile_size=tile_size, means2d_delta=means2d_delta, max_pairs=max_pairs)
        check_values(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat,
                     K=K, background=background, means2d_delta=means2d_delta)
    return _rasterize_jit(means, quats, scales, opacities, colors, viewmat, K, width, height, near=near, far=far,
                          background=background, antialiased=antialiased, eps2d=eps2d, tile_size=tile_size,
                          max_pairs=max_pairs, means2d_delta=means2d_delta, lens=lens, compositor=compositor,
                          sparse_channels=sparse_channels)


def _rasterize(
    means: jax.Array,
    quats: jax.Array,
    scales: jax.Array,
    opacities: jax.Array,
    colors: jax.Array,
    viewmat: jax.Array,
    K: jax.Array,
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: jax.Array | None = None,
    antialiased: bool = False,
    eps2d: float = 0.3,
    tile_size: int = 16,
    max_pairs: int | None = None,
    means2d_delta: jax.Array | None = None,
    lens: Lens | None = None,
    compositor: Compositor = Compositor(),
    sparse_channels: SparseChannels | None = None,
) -> RenderOutput:
    """:func:`rasterize` without its host-side checks (traced once per static configuration)."""
    check_shapes(means, quats, scales, opacities, colors, viewmat, K, width, height, background=background,
                 tile_size=tile_size, means2d_delta=means2d_delta, max_pairs=max_pairs)
    num_gaussians, channels = colors.shape
    if num_gaussians == 0:  # nothing to draw: the background (one invisible Gaussian keeps every shape non-empty)
        return _rasterize_nothing(means, quats, scales, opacities, colors, viewmat, K, width, height, near=near,
                                  far=far, background=background, antialiased=antialiased, eps2d=eps2d,
                                  tile_size=tile_size, max_pairs=max_pairs, means2d_delta=means2d_delta, lens=lens,
                                  compositor=compositor, sparse_channels=sparse_channels)
    grid = TileGrid(int(width), int(height), int(tile_size))
    if sparse_channels is not None and not (isinstance(sparse_channels, SparseChannels)
                                            and 1 <= int(sparse_channels.count) <= channels):
        raise ValueError(f"sparse_channels must be a SparseChannels with 1 <= count <= C = {channels}, "
                         f"got {sparse_channels!r:.120}")
    if max_pairs is None:
        max_pairs = default_max_pairs(num_gaussians, width, height, tile_size)
    dtype = means.dtype
    proj = project_gaussians(
        means, quats, scales, opacities, viewmat.astype(dtype), K.astype(dtype),
        width, height, near=near, far=far, eps2d=eps2d, antialiased=antialiased, lens=lens,
    )
    ellipse = isinstance(compositor, Compositor) and compositor.tiles == "ellipse"  # else every tile of the box
    isect = intersect_tiles(proj.means2d, proj.radii, proj.depths, proj.visible, grid, max_pairs,
                            *((proj.conics, proj.opacities) if ellipse else ()))
    order = isect.order
    means2d = proj.means2d if means2d_delta is None else proj.means2d + means2d_delta
    depth = jnp.where(proj.visible, proj.depths, 0.0)
    dense = channels - (0 if sparse_channels is None else int(sparse_channels.count))  # composited everywhere
    features = jnp.concatenate([colors[:, :dense].astype(dtype), depth[:, None]], axis=-1)
    sorted_inputs = (means2d[order], proj.conics[order], proj.opacities[order], features[order],
                     isect.pair_gaussians, isect.tile_starts, isect.tile_ends)
    if not isinstance(compositor, Compositor):
        raise TypeError(f"compositor must be a cusgs_jax.splat.Compositor, got {type(compositor).__name__}: "
                        "e.g. Compositor(backend='jax', chunk_size=16)")
    sparse = ()  # (sorted sparse colours [G, Q], [T, K] slots) for the JAX compositor
    if sparse_channels is not None:
        slots, slot_pixels = sparse_channels.slots(grid)
        slot_pixels = jnp.asarray(slot_pixels.reshape(-1))
        sparse = (colors[:, dense:].astype(dtype)[order], jnp.asarray(slots))
    if resolve_backend(compositor.backend) == "pallas":
        interpret = jax.default_backend() != "gpu"  # Triton needs an NVIDIA (or ROCm) GPU
        if sparse:  # every channel everywhere, then read at the listed pixels
            everything = jnp.concatenate([sorted_inputs[3], sparse[0]], axis=-1)
            out = composite_tiles_pallas(grid, PALLAS_BATCH, interpret, *sorted_inputs[:3], everything,
                                         *sorted_inputs[4:])
            listed = jnp.asarray(np.minimum(slots, grid.tile_size ** 2 - 1))[..., None]
            out = out._replace(colors=out.colors[..., :dense + 1],
                               sparse=jnp.take_along_axis(out.colors[..., dense + 1:], listed, axis=1))
        else:
            out = composite_tiles_pallas(grid, PALLAS_BATCH, interpret, *sorted_inputs)
    else:
        lanes = default_lanes(grid.num_tiles) if compositor.lanes is None else int(compositor.lanes)
        out = composite_tiles(grid, int(compositor.chunk_size), lanes, *sorted_inputs, *sparse)
    color_fg = _tiles_to_image(out.colors, grid)
    trans = _tiles_to_image(out.transmittance, grid)
    if background is None:
        image = color_fg[..., :dense]
    else:
        image = color_fg[..., :dense] + trans[..., None] * jnp.asarray(background, dtype)[:dense]
    if sparse_channels is not None:  # [T, K, Q] → the listed pixels of an [H, W, Q] image of zeros
        count = channels - dense
        values = out.sparse.reshape(-1, count)
        if background is not None:
            values = values + trans.reshape(-1)[jnp.minimum(slot_pixels, width * height - 1)][:, None] \
                * jnp.asarray(background, dtype)[dense:]
        sparse_image = jnp.zeros((width * height, count), dtype).at[slot_pixels].set(values, mode="drop")
        image = jnp.concatenate([image, sparse_image.reshape(height, width, count)], axis=-1)
    significance = jnp.zeros_like(out.significance).at[order].set(out.significance)
    hits = jnp.zeros_like(out.hits).at[order].set(out.hits)
    radii = jnp.minimum(proj.radii, float(2**30)).astype(jnp.int32)
    return RenderOutput(
        image=image,
        alpha=1.0 - trans,
        depth=color_fg[..., dense],
        n_contrib=_tiles_to_image(out.n_contrib, grid),
        means2d=means2d,
        radii=radii,
        visible=proj.visible,
        significance=jax.lax.stop_gradient(significance),
        hits=hits,
        overflow=isect.overflow,
        num_pairs=isect.num_pairs,
    )


_rasterize.__name__ = _rasterize.__qualname__ = "rasterize"  # compile logs and profiles say jit(rasterize)
_rasterize_jit = jax.jit(
    _rasterize,
    static_argnames=tuple(name for name in RASTERIZE_STATIC_ARGNAMES if name != "validate"),
)


def _rasterize_nothing(means, quats, scales, opacities, colors, viewmat, K, width, height, *, means2d_delta,
                       **kwargs) -> RenderOutput:
    """:func:`rasterize` of G = 0 Gaussians: one fully transparent Gaussian is drawn, and the
    per-Gaussian fields come back with G = 0 rows (so gradients keep the inputs' empty shapes)."""
    def one_more(x, value):
        return jnp.concatenate([x, jnp.full((1,) + x.shape[1:], value, x.dtype)])

    delta = None if means2d_delta is None else one_more(means2d_delta, 0.0)
    out = _rasterize_jit(one_more(means, 0.0), one_more(quats, 1.0), one_more(scales, 1e-3),
                         one_more(opacities, 0.0), one_more(colors, 0.0), viewmat, K, width, height,
                         means2d_delta=delta, **kwargs)
    return out._replace(means2d=out.means2d[:0], radii=out.radii[:0], visible=out.visible[:0],
                        significance=out.significance[:0], hits=out.hits[:0])


def rasterize_batch(
    means, quats, scales, opacities, colors, viewmats, Ks, width: int, height: int, *, validate: bool = True,
    **kwargs,
) -> RenderOutput:
    """Render one scene from B cameras in one call (``jax.vmap`` of :func:`rasterize`), as gsplat's
    ``rasterization(..., viewmats [B, 4, 4], Ks, ...)``.

    Under ``jax.jit`` the static arguments must be static as for :func:`rasterize`: use
    :data:`rasterize_batch_jit` or ``jax.jit(rasterize_batch, static_argnames=RASTERIZE_STATIC_ARGNAMES)``.

    Args:
      viewmats: [B, 4, 4] world→camera matrices, one per view (for one view, :func:`rasterize`).
      Ks: [3, 3] intrinsics shared by every view (broadcast, as gsplat does), or [B, 3, 3] one per view.
      validate: outside jit, check the inputs' values once for the whole batch (as :func:`rasterize`).
      kwargs: :func:`rasterize`'s keywords, shared by every view (``background`` [C], ``lens``, ...).
      other arguments as :func:`rasterize`.
    Returns:
      :class:`RenderOutput` with a leading batch axis B on every field.
    Raises:
      ValueError: as :func:`rasterize`, and ``viewmats`` or ``Ks`` of the wrong shape (e.g. one [4, 4] view).
    """
    _refuse_keywords("rasterize_batch", {k: v for k, v in kwargs.items() if k not in _RASTERIZE_KEYWORDS})
    _require_static("rasterize_batch", width=width, height=height, validate=validate,
                    **{k: v for k, v in kwargs.items() if k in RASTERIZE_STATIC_ARGNAMES})
    means, quats, scales, opacities, colors, viewmats, Ks = (
        _as_array(a) for a in (means, quats, scales, opacities, colors, viewmats, Ks))
    for name in ("background", "means2d_delta"):
        if name in kwargs:
            kwargs[name] = _as_array(kwargs[name])
    if tuple(viewmats.shape) == (4, 4):
        raise ValueError("viewmats must have shape [B, 4, 4] (one world→camera matrix per view), got one [4, 4] "
                         "matrix: use rasterize(...) for one view, or stack the views into [B, 4, 4] "
                         "(viewmat[None] for a batch of one)")
    if len(viewmats.shape) != 3 or tuple(viewmats.shape[1:]) != (4, 4):
        raise ValueError(f"viewmats must have shape [B, 4, 4], got {list(viewmats.shape)}")
    views = viewmats.shape[0]
    if tuple(Ks.shape) == (3, 3):
        k_axis = None  # one K for every view
    elif tuple(Ks.shape) == (views, 3, 3):
        k_axis = 0
    else:
        raise ValueError(f"Ks must have shape [3, 3] (shared by all {views} views) or [{views}, 3, 3] (one per "
                         f"view), got {list(Ks.shape)}")
    if validate and not _is_traced(means, quats, scales, opacities, colors, viewmats, Ks, kwargs):
        one_view, one_K = jax.ShapeDtypeStruct((4, 4), viewmats.dtype), jax.ShapeDtypeStruct((3, 3), Ks.dtype)
        check_shapes(means, quats, scales, opacities, colors, one_view, one_K, width, height,
                     background=kwargs.get("background"), tile_size=kwargs.get("tile_size", 16),
                     means2d_delta=kwargs.get("means2d_delta"), max_pairs=kwargs.get("max_pairs"))
        check_values(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats,
                     Ks=Ks, background=kwargs.get("background"), means2d_delta=kwargs.get("means2d_delta"))

    def one(viewmat, K):
        return rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, validate=False,
                         **kwargs)

    return jax.vmap(one, in_axes=(0, k_axis))(viewmats, Ks)


_RASTERIZE_KEYWORDS = frozenset(
    name for name, parameter in inspect.signature(rasterize).parameters.items()
    if parameter.kind is inspect.Parameter.KEYWORD_ONLY and name != "validate"
)

rasterize_jit = jax.jit(rasterize, static_argnames=RASTERIZE_STATIC_ARGNAMES)
"""``jax.jit(rasterize, static_argnames=RASTERIZE_STATIC_ARGNAMES)``: :func:`rasterize` for your own jitted code
(the same image bit for bit; inside jit the values are not checked — see :func:`rasterize`)."""

rasterize_batch_jit = jax.jit(rasterize_batch, static_argnames=RASTERIZE_STATIC_ARGNAMES)
"""``jax.jit(rasterize_batch, static_argnames=RASTERIZE_STATIC_ARGNAMES)``."""


def check_shapes(means, quats, scales, opacities, colors, viewmat, K, width, height, *, background=None,
                 tile_size: int = 16, means2d_delta=None, max_pairs: int | None = None) -> None:
    """Check the rasteriser inputs' shapes, dtypes and static sizes (arrays or tracers: :func:`rasterize`
    runs it while tracing, so a wrong shape is a ValueError naming the argument, not a wrong image).

    Raises:
      ValueError: naming the offending argument, its shape and what was expected.
    """
    if len(means.shape) != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape [G, 3], got {list(means.shape)}")
    g = means.shape[0]
    if len(colors.shape) != 2 or colors.shape[1] < 1:
        raise ValueError(f"colors must have shape [G, C] with C >= 1, got {list(colors.shape)}")
    c = colors.shape[1]
    arrays = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat, K=K,
                  background=background, means2d_delta=means2d_delta)
    expected = dict(means=(g, 3), quats=(g, 4), scales=(g, 3), opacities=(g,), colors=(g, c),
                    viewmat=(4, 4), K=(3, 3), background=(c,), means2d_delta=(g, 2))
    for name, arr in arrays.items():
        if arr is None:
            continue
        if tuple(arr.shape) != expected[name]:
            raise ValueError(f"{name} must have shape {list(expected[name])} (G={g}, C={c}), got {list(arr.shape)}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{name} must be a floating-point array, got dtype {arr.dtype}")
    for name, value in (("width", width), ("height", height), ("tile_size", tile_size)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) <= 0:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if max_pairs is not None and (isinstance(max_pairs, bool) or not isinstance(max_pairs, (int, np.integer))
                                  or int(max_pairs) <= 0):
        raise ValueError(f"max_pairs must be a positive int or None (None: default_max_pairs), got {max_pairs!r}")


@jax.jit
def _values_ok(arrays: dict) -> jax.Array:
    """[] bool: every array finite, scales ≥ 0, opacities in [0, 1] (one scalar to bring back)."""
    flags = [jnp.all(jnp.isfinite(a)) for a in arrays.values()]
    if "scales" in arrays:
        flags.append(jnp.all(arrays["scales"] >= 0))
    if "opacities" in arrays:
        flags.append(jnp.all((arrays["opacities"] >= 0) & (arrays["opacities"] <= 1)))
    return jnp.all(jnp.stack(flags))


def _first_index(bad: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(bad)[0])


def _check_values_host(arrays: dict) -> None:
    """:func:`check_values` on NumPy arrays (None entries skipped)."""
    for name, arr in arrays.items():
        if arr is None:
            continue
        bad = ~np.isfinite(arr)
        if bad.any():
            raise ValueError(f"{name} has {int(bad.sum())} non-finite value(s) (NaN or Inf), "
                             f"first at index {_first_index(bad)}; fix or drop those entries before rendering")
    scales, opacities = arrays.get("scales"), arrays.get("opacities")
    if scales is not None and (bad := scales < 0).any():
        raise ValueError(f"scales must be non-negative linear standard deviations, got {int(bad.sum())} negative "
                         f"value(s), first at index {_first_index(bad)} "
                         "(pass exp(log_scales) if you store logarithms)")
    if opacities is not None and (bad := (opacities < 0) | (opacities > 1)).any():
        raise ValueError(f"opacities must lie in [0, 1], got {int(bad.sum())} value(s) outside, first "
                         f"{float(opacities[_first_index(bad)])} at index {_first_index(bad)} "
                         "(apply a sigmoid to logits first)")


def check_values(**arrays) -> None:
    """Check concrete rasteriser inputs' values: every array finite, ``scales`` ≥ 0, ``opacities`` in [0, 1].

    Arrays are passed by name (None skipped). NumPy arrays are checked on the host in one pass; when any is a
    JAX array, a few reductions run where the arrays are and one bool comes back (the details are read only
    when something is wrong). :func:`rasterize` runs it outside jit.

    Raises:
      ValueError: naming the argument, how many entries are wrong and the first one's index.
    """
    arrays = {name: arr for name, arr in arrays.items() if arr is not None}
    if not arrays:
        return
    if any(isinstance(arr, jax.Array) for arr in arrays.values()):
        if bool(jax.device_get(_values_ok(arrays))):
            return
    _check_values_host({name: np.asarray(arr) for name, arr in arrays.items()})


def check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height,
                 background=None) -> None:
    """Validate rasteriser inputs on the host with clear messages: what :func:`rasterize` checks outside jit,
    and that ``viewmat``'s last row is [0, 0, 0, 1] and ``K``'s focal lengths are positive. Call it on the
    concrete inputs before (or instead of) checking inside jit.

    Raises:
      ValueError: naming the offending argument, its shape or how many
        non-finite entries it has, and what was expected.
    """
    arrays = dict(means=means, quats=quats, scales=scales, opacities=opacities,
                  colors=colors, viewmat=viewmat, K=K)
    if background is not None:
        arrays["background"] = background
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    check_shapes(*(arrays[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")),
                 width, height, background=arrays.get("background"))
    _check_values_host(arrays)
    if not np.allclose(arrays["viewmat"][3], [0, 0, 0, 1]):
        raise ValueError(f"viewmat's last row must be [0, 0, 0, 1], got {arrays['viewmat'][3]}")
    if arrays["K"][0, 0] <= 0 or arrays["K"][1, 1] <= 0:
        raise ValueError("K must have positive focal lengths K[0,0] and K[1,1]")
