"""Baking a scaffold into plain 3D Gaussians: the standard 3DGS PLY's content (docs/formats.md#baking-a-scaffold).

A Scaffold-GS anchor's N Gaussians depend on the view: the decoder heads take the
unit direction camera→anchor ``d`` (opacity, covariance, colour) and a
per-training-camera appearance embedding (colour). A standard PLY stores one
Gaussian with SH colours. Scaffold-GS PR #113's recipe, with the choices it
leaves open made here:

* **Directions.** ``D`` directions on a Fibonacci sphere (:func:`fibonacci_sphere`,
  default 64), the same for every anchor. Each anchor is decoded with
  :func:`cusgs_jax.model.decode.decode_gaussians` once per direction, the
  camera put at ``x_v − d`` (per anchor, so every anchor sees exactly ``d``; the
  decoder only uses the normalised direction, so the distance does not matter).
* **Training cameras** (when given, as the exporter does whenever the run or its
  scene records them): opacity and shape are averaged over the training
  cameras whose frustum holds the anchor (the views the decoder was trained
  on for it, decoded from each camera's own position) instead of over the
  sphere, whose other directions the MLPs were never trained on (the cameras that
  see the anchor beat all training cameras, which beat the sphere:
  docs/benchmarks.md#baking). An anchor that no camera holds is averaged over every camera.
* **Appearance.** The colour head's per-camera embedding is the **mean of the
  training embeddings**: an exported model is seen from views that are none of
  the training cameras, and the mean belongs to no camera in particular (the
  held-out evaluation instead borrows the nearest training camera's).
* **Colour → SH.** Least squares per Gaussian and channel over the D sphere
  directions: ``c = B⁺ (colour − 0.5)`` with ``B = sh_basis(dirs)`` [D, K] and its
  pseudo-inverse computed once (:func:`sh_fit_matrix`), so that
  ``0.5 + Σ_k c_k Y_k(d) ≈ colour(d)`` (:func:`cusgs_jax.splat.sh.sh_to_rgb`).
  One matrix for all Gaussians, exact for colours that are SH of the degree
  (tested), and well-posed on the whole sphere, where a fit to the few
  directions of the training cameras would leave the high orders free to swing
  between them. (Rendering the exact decoded geometry with these SH colours
  loses nothing measurable: docs/benchmarks.md#baking.)
* **Opacity.** ``tanh`` opacities ≤ 0 switch a Gaussian off. The baked opacity
  is the mean of ``max(o, 0)`` over the views (cameras, or sphere directions). A
  Gaussian that is on from few of them gets a small opacity instead of a full
  one everywhere (it scored above the mean over the views where it is on, the
  self-weighted mean Σo²/Σo and the maximum: docs/benchmarks.md#baking). A
  Gaussian whose opacity is ≤ ``min_opacity`` from every view is dropped.
* **Scale and rotation.** The covariance head depends on the direction too, and
  this is where the bake loses most (swapping one baked part at a time into the
  Gaussians decoded for each held-out view: docs/benchmarks.md#baking).
  **With training cameras** (the exporter's default) the baked shape is the
  moment-matched Gaussian, the mean of the decoded covariances
  ``R diag(σ²) Rᵀ`` weighted by ``max(o, 0)`` (:func:`mean_covariance`), which
  scored above the mean rotation with geometric-mean scales below, arithmetic-mean
  scales, ``o²`` weights and the eigenvector quaternion mean. **Over the sphere**
  the mean shape is kept: scales by their weighted geometric mean (the mean of
  log σ), rotations by the weighted mean of the unit quaternions, each first
  given the sign of the most opaque view's (q and −q are one rotation), then
  normalised (:func:`mean_shape`); there the moment-matched covariance inflates
  the ellipsoids that turn or change size with the view, and blurs.
* **Position** ``μ = x_v + Δx·exp(s[:3])`` does not depend on the view.

Everything here is pure; :func:`bake_anchors` is jitted over a chunk of anchors.

Naming (:mod:`cusgs_jax.types`): A anchors in the chunk, N offsets per anchor,
G = A·N Gaussians, D directions, K = (d+1)² SH coefficients, E appearance size.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import DecoderConfig
from cusgs_jax.model.anchors import AnchorParams
from cusgs_jax.model.decode import decode_gaussians, frustum_mask
from cusgs_jax.splat.lens import Lens
from cusgs_jax.splat.project import normalize_quats, quats_to_rotmats
from cusgs_jax.model.splats import SplatModel
from cusgs_jax.splat.sh import MAX_SH_DEGREE, num_sh_coeffs, sh_basis, sh_degree
from cusgs_jax.precision import HIGHEST
from cusgs_jax.types import camera_center as camera_center_of

__all__ = ["BakeSummary", "BakedGaussians", "bake_anchors", "bake_splats", "fibonacci_sphere", "fit_sh",
           "matrix_to_quat", "mean_covariance", "mean_shape", "sh_fit_matrix", "to_colmap_frame", "rotate_sh"]

OPACITY_EPS = 1e-6  # stored opacities are clipped to (eps, 1 − eps) before the logit
MAX_CAMERAS = 256  # training cameras that opacity and shape are averaged over (evenly spread subset)


def fibonacci_sphere(count: int) -> np.ndarray:
    """[D, 3] float32 unit vectors spread evenly over the sphere (golden-angle spiral).

    ``z_i = 1 − (2i + 1)/D``, azimuth ``i·π(3 − √5)``: no two coincide and no pole
    is sampled twice, for any D ≥ 1.
    """
    if count < 1:
        raise ValueError(f"need at least one direction, got {count}")
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1).astype(np.float32)


def sh_fit_matrix(dirs, degree: int) -> np.ndarray:
    """[K, D] float32 pseudo-inverse of the SH basis at ``dirs`` [D, 3] (computed in float64).

    ``fit_sh(colors, sh_fit_matrix(dirs, d))`` is the least-squares SH fit; with
    D ≥ K well-spread directions the basis has full column rank and the fit of
    colours that are SH of degree ≤ d is exact.
    """
    basis = np.asarray(sh_basis(jnp.asarray(np.asarray(dirs, np.float64)), degree), np.float64)
    return np.linalg.pinv(basis).astype(np.float32)


def fit_sh(colors: jax.Array, fit: jax.Array) -> jax.Array:
    """Least-squares SH coefficients of colours seen from the fit's directions.

    Args:
      colors: [..., D, 3] RGB per direction.
      fit: [K, D] from :func:`sh_fit_matrix`.
    Returns:
      [..., K, 3] coefficients (coefficient-major, ``[..., 0, :]`` is ``f_dc``)
      minimising ``Σ_d ‖0.5 + Σ_k c_k Y_k(d) − colour(d)‖²``.
    """
    return jnp.einsum("kd,...dc->...kc", fit, colors - 0.5, precision=HIGHEST)


def mean_shape(quats: jax.Array, scales: jax.Array, weights: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One Gaussian shape from the shapes decoded in D directions.

    Args:
      quats: [D, G, 4] wxyz (any norm: the decoder's raw output); scales: [D, G, 3] σ > 0;
      weights: [D, G] ≥ 0 (a Gaussian whose weights are all 0 gets equal weights).
    Returns:
      (quats [G, 4] unit wxyz: the weighted mean of the unit quaternions after
      flipping each to the sign of the highest-weight direction's, normalised;
      scales [G, 3]: the weighted geometric mean ``exp(Σ_d w_d log σ_d)``).
    """
    total = jnp.sum(weights, axis=0)  # [G]
    w = jnp.where(total > 0, weights / jnp.where(total > 0, total, 1.0), 1.0 / weights.shape[0])
    unit = normalize_quats(quats)
    ref = jnp.take_along_axis(unit, jnp.argmax(w, axis=0)[None, :, None], axis=0)  # [1, G, 4]
    aligned = jnp.where(jnp.sum(unit * ref, axis=-1, keepdims=True) < 0, -unit, unit)
    quat = normalize_quats(jnp.einsum("dg,dgc->gc", w, aligned, precision=HIGHEST))
    scale = jnp.exp(jnp.einsum("dg,dgc->gc", w, jnp.log(jnp.maximum(scales, 1e-30)), precision=HIGHEST))
    return quat, scale


_AXIS_FLIPS = np.array([[1, 1, 1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1]], np.float32)
"""Column sign patterns of determinant +1: R·diag(f) is the same ellipsoid (its axes are lines)."""


def matrix_to_quat(rot: jax.Array) -> jax.Array:
    """[..., 4] unit wxyz quaternions of rotation matrices [..., 3, 3] whose trace is ≥ −1 + 1/4.

    ``w = ½√(1 + tr R)`` and ``(x, y, z) = (R₂₁ − R₁₂, R₀₂ − R₂₀, R₁₀ − R₀₁) / 4w``: well
    conditioned when ``w`` is not small, which :func:`mean_covariance` ensures (trace ≥ 0).
    """
    w = 0.5 * jnp.sqrt(jnp.maximum(1.0 + jnp.trace(rot, axis1=-2, axis2=-1), 1e-12))
    xyz = jnp.stack([rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0],
                     rot[..., 1, 0] - rot[..., 0, 1]], axis=-1) / (4.0 * w[..., None])
    return normalize_quats(jnp.concatenate([w[..., None], xyz], axis=-1))


def mean_covariance(quats: jax.Array, scales: jax.Array, weights: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One Gaussian shape from decoded shapes: the weighted mean covariance (moment matching).

    ``Σ = Σ_v w_v R_v diag(σ_v²) R_vᵀ`` with the weights normalised per Gaussian (all zero: equal),
    then ``Σ = R diag(σ²) Rᵀ`` by eigen-decomposition, ``R`` made a proper rotation and given the
    column signs (:data:`_AXIS_FLIPS`, which leave the ellipsoid unchanged) of largest trace, so
    that its quaternion is well conditioned.

    Args:
      quats: [V, G, 4] wxyz (any norm); scales: [V, G, 3] σ > 0; weights: [V, G] ≥ 0.
    Returns:
      (quats [G, 4] unit wxyz, scales [G, 3] σ ≥ 1e-15): exactly the input shape when every
      view with a weight has the same one.
    """
    total = jnp.sum(weights, axis=0)
    w = jnp.where(total > 0, weights / jnp.where(total > 0, total, 1.0), 1.0 / weights.shape[0])
    rot = quats_to_rotmats(normalize_quats(quats))  # [V, G, 3, 3]
    cov = jnp.einsum("vg,vgij,vgj,vgkj->gik", w, rot, jnp.square(scales), rot, precision=HIGHEST)
    values, vectors = jnp.linalg.eigh(0.5 * (cov + jnp.swapaxes(cov, -1, -2)))
    proper = jnp.sign(jnp.linalg.det(vectors))
    vectors = vectors.at[..., 2].multiply(jnp.where(proper == 0, 1.0, proper)[..., None])
    diag = jnp.diagonal(vectors, axis1=-2, axis2=-1)  # [G, 3]
    flips = jnp.asarray(_AXIS_FLIPS)[jnp.argmax(jnp.matmul(diag, jnp.asarray(_AXIS_FLIPS).T, precision=HIGHEST), axis=-1)]  # [G, 3]
    quat = matrix_to_quat(vectors * flips[:, None, :])
    return quat, jnp.sqrt(jnp.maximum(values, 1e-30))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BakedGaussians:
    """View-independent Gaussians of a chunk of anchors, in the training (normalised) frame.

    Attributes:
      means: [G, 3]; quats: [G, 4] unit wxyz; scales: [G, 3] linear σ;
      opacities: [G] baked opacity in [0, 1): the mean of max(decoded opacity, 0) over the directions;
      sh: [G, K, 3] SH coefficients;
      on_fraction: [G] fraction of the directions in which the Gaussian is on (opacity > 0);
      max_opacity: [G] largest decoded opacity over the directions (≤ 0: never visible);
      alive: [G] the owning anchor is alive (padding slots of a compacted model are not).
    """

    means: jax.Array
    quats: jax.Array
    scales: jax.Array
    opacities: jax.Array
    sh: jax.Array
    on_fraction: jax.Array
    max_opacity: jax.Array
    alive: jax.Array


@functools.partial(jax.jit, static_argnames=("cfg", "width", "height", "margin"))
def bake_anchors(decoder: dict, anchor_params: AnchorParams, centers: jax.Array, alive: jax.Array,
                 appearance: jax.Array | None, dirs: jax.Array, fit: jax.Array, cfg: DecoderConfig,
                 viewmats: jax.Array | None = None, Ks: jax.Array | None = None, width: int = 0, height: int = 0,
                 margin: float = 0.15, lenses: Lens | None = None) -> BakedGaussians:
    """Decode a chunk of anchors from every direction (and training camera) and bake each Gaussian.

    Args:
      decoder: the decoder heads (``nets["decoder"]``).
      anchor_params: [A, …] the chunk's learnable arrays; centers: [A, 3]; alive: [A] bool.
      appearance: [E] embedding for the colour head (e.g. the mean training
        embedding), or None when the model has none.
      dirs: [D, 3] unit directions camera→anchor (:func:`fibonacci_sphere`): the SH fit,
        and opacity and shape when no cameras are given.
      fit: [K, D] :func:`sh_fit_matrix` of ``dirs``.
      cfg: the decoder's static shape.
      viewmats, Ks: [V, 4, 4] world→camera and [V, 3, 3] intrinsics of the training
        cameras (static ``width``, ``height``): opacity and shape are then averaged over
        the cameras whose frustum (widened by ``margin``, as in training) holds the
        anchor — every camera for an anchor that none holds. None: over ``dirs``.
      lenses: the cameras' lenses (a batched :class:`~cusgs_jax.splat.lens.Lens`, coeffs [V, 6]) of a
        ``data.undistort=lens`` run, so that "holds" is the frustum through the lens as in training; or None.
    Returns:
      :class:`BakedGaussians` with G = A·N (anchor-major, as the decoder orders them).
    """
    n = cfg.n_offsets

    def one_direction(d):
        # the camera at x_v − d for every anchor: decode_gaussians normalises centers − camera = d
        g = decode_gaussians(decoder, anchor_params, centers, alive, centers - d, appearance, cfg)
        return g.opacities, g.colors, g.scales, g.quats

    opacity, colors, scales, quats = jax.lax.map(one_direction, dirs)  # [D, G], [D, G, 3], [D, G, 3], [D, G, 4]
    means = decode_gaussians(decoder, anchor_params, centers, alive, centers - dirs[0], appearance, cfg).means
    sh = fit_sh(jnp.moveaxis(colors, 0, 1), fit)  # [G, D, 3] → [G, K, 3]
    if viewmats is None:
        seen = jnp.ones_like(opacity)
    else:
        def one_camera(view_k_lens):
            view, K, lens = view_k_lens
            camera_center = camera_center_of(view)
            g = decode_gaussians(decoder, anchor_params, centers, alive, camera_center, appearance, cfg)
            inside = frustum_mask(centers, view, K, width, height, margin=margin, lens=lens)
            return g.opacities, g.scales, g.quats, jnp.repeat(inside, n)

        opacity, scales, quats, inside = jax.lax.map(one_camera, (viewmats, Ks, lenses))  # [V, G], …
        seen = jnp.where(jnp.any(inside, axis=0), inside, True).astype(opacity.dtype)
    # decode_gaussians zeroes switched-off Gaussians (tanh ≤ 0) and dead anchors: opacity = max(o, 0)
    views = jnp.sum(seen, axis=0)
    # cameras: the moment-matched covariance; the sphere: the mean rotation and geometric-mean scales (module doc)
    quat, scale = (mean_shape if viewmats is None else mean_covariance)(quats, scales, opacity * seen)
    return BakedGaussians(means=means, quats=quat, scales=scale, opacities=jnp.sum(opacity * seen, axis=0) / views,
                          sh=sh, on_fraction=jnp.sum((opacity > 0) * seen, axis=0) / views,
                          max_opacity=jnp.max(opacity * seen, axis=0), alive=jnp.repeat(alive, n))


def to_colmap_frame(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, sh: np.ndarray, world):
    """Gaussians from the normalised training frame ``p' = s·Q(p − c)`` back to the COLMAP frame.

    ``p = Qᵀ p' / s + c`` (:meth:`cusgs_jax.data.normalize.WorldTransform.to_colmap`, float64),
    ``log σ = log σ' − log s``; with a rotation Q (``data.align=principal``) the Gaussians'
    rotations become ``Qᵀ R'`` and their SH colours are rotated with them: the colour seen
    along a COLMAP-frame direction d is the trained one along ``Q d``. The SH rotation is the
    exact linear map ``M = B(D)⁺ B(D Qᵀ)`` over well-spread directions D (SH of each degree
    are closed under rotation, so the least-squares fit reproduces them exactly).

    Args:
      means: [G, 3]; log_scales: [G, 3]; quats: [G, 4] wxyz; sh: [G, K, 3];
      world: :class:`~cusgs_jax.data.normalize.WorldTransform`.
    Returns:
      (means [G, 3], log_scales [G, 3], quats [G, 4], sh [G, K, 3]), float64; without a rotation
      the quaternions and SH are returned unchanged.
    """
    out_means, out_scales = world.to_colmap(means), np.asarray(log_scales, np.float64) - np.log(world.scale)
    rotation = world.matrix
    quats = np.asarray(quats, np.float64)
    sh = np.asarray(sh, np.float64)
    if np.allclose(rotation, np.eye(3)):
        return out_means, out_scales, quats, sh
    return out_means, out_scales, _rotate_quats(rotation.T, quats), rotate_sh(sh, rotation)


def _matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """[4] wxyz unit quaternion of a rotation matrix [3, 3] (Shepperd's method)."""
    trace = np.trace(m)
    if trace > 0:
        w = np.sqrt(1.0 + trace) / 2
        return np.array([w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)])
    i = int(np.argmax(np.diag(m)))
    j, k = (i + 1) % 3, (i + 2) % 3
    r = np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
    q = np.zeros(4)
    q[1 + i] = r / 2
    q[1 + j] = (m[j, i] + m[i, j]) / (2 * r)
    q[1 + k] = (m[k, i] + m[i, k]) / (2 * r)
    q[0] = (m[k, j] - m[j, k]) / (2 * r)
    return q


def _rotate_quats(m: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """[G, 4] wxyz quaternions of ``m · R(q)`` (Hamilton product q_m ⊗ q)."""
    a = _matrix_to_quat(m)
    w, x, y, z = np.moveaxis(quats, -1, 0)
    return np.stack([a[0] * w - a[1] * x - a[2] * y - a[3] * z,
                     a[0] * x + a[1] * w + a[2] * z - a[3] * y,
                     a[0] * y - a[1] * z + a[2] * w + a[3] * x,
                     a[0] * z + a[1] * y - a[2] * x + a[3] * w], axis=-1)


def rotate_sh(sh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """[G, K, 3] SH coefficients c' with ``Σ c'_k Y_k(d) = Σ c_k Y_k(Q d)`` for every unit d (float64).

    Args:
      sh: [G, K, 3]; rotation: [3, 3] Q.
    """
    degree = sh_degree(sh.shape[1])
    dirs = fibonacci_sphere(256).astype(np.float64)
    basis = np.asarray(sh_basis(jnp.asarray(dirs), degree), np.float64)
    turned = np.asarray(sh_basis(jnp.asarray(dirs @ np.asarray(rotation, np.float64).T), degree), np.float64)
    mix = np.linalg.lstsq(basis, turned, rcond=None)[0]  # [K, K]
    return np.einsum("kj,gjc->gkc", mix, sh)


@dataclasses.dataclass(frozen=True)
class BakeSummary:
    """What :func:`bake_splats` kept and dropped (host-side counts)."""

    gaussians: int  # written
    considered: int  # alive anchors × N
    dropped_never_visible: int  # opacity ≤ min_opacity in every direction
    sh_degree: int
    directions: int  # sphere directions (SH fit; opacity and shape without cameras)
    cameras: int  # training cameras that opacity and shape were averaged over (0: the sphere)


def bake_splats(anchors, nets: dict, cfg: DecoderConfig, *, sh_degree: int = 3, directions: int = 64,
                min_opacity: float = 0.005, appearance=None, cameras=None, max_cameras: int = MAX_CAMERAS,
                frustum_margin: float = 0.15, chunk_anchors: int = 1024, progress=None):
    """Bake a scaffold into a :class:`~cusgs_jax.io.ply.SplatModel` (training frame), chunk by chunk.

    Args:
      anchors: :class:`~cusgs_jax.model.anchors.AnchorState` (compacted or not; dead slots are skipped).
      nets: {"decoder", "appearance"?: [V, E], …}.
      cfg: the decoder's static shape (``ModelConfig.decoder()``).
      sh_degree: 0–3; directions: D ≥ (sh_degree+1)² sphere directions.
      min_opacity: drop Gaussians whose decoded opacity is ≤ this in every direction (every
        training camera that sees the anchor, with ``cameras``).
      appearance: [E] colour-head embedding; None: the mean of ``nets["appearance"]`` (if any).
      cameras: the training cameras as one batched :class:`~cusgs_jax.types.Camera`
        (K [V, 3, 3], world_to_camera [V, 4, 4]) in the anchors' frame, or None: opacity and
        shape are then averaged over the cameras that see each anchor instead of the sphere;
        at most ``max_cameras`` of them, evenly spread over the list.
      frustum_margin: the training frustum margin (``model.frustum_margin``).
      chunk_anchors: anchors decoded per jitted call (memory ∝ chunk·N·(D + V)).
      progress: optional ``callable(anchors_done)`` called after each chunk (e.g. a tqdm update).
    Returns:
      (SplatModel with opacity logits clipped to (1e-6, 1 − 1e-6), log scales and
      unit wxyz quaternions, all float32; :class:`BakeSummary`).
    """

    if sh_degree not in range(MAX_SH_DEGREE + 1):
        raise ValueError(f"sh_degree must be 0..{MAX_SH_DEGREE}, got {sh_degree}")
    if directions < num_sh_coeffs(sh_degree):
        raise ValueError(f"{directions} directions cannot determine the {num_sh_coeffs(sh_degree)} SH coefficients "
                         f"of degree {sh_degree}: use at least that many")
    if appearance is None and "appearance" in nets and cfg.appearance_dim:
        appearance = jnp.mean(nets["appearance"], axis=0)
    if not cfg.appearance_dim:
        appearance = None
    dirs = fibonacci_sphere(directions)
    fit = sh_fit_matrix(dirs, sh_degree)
    views = {}
    if cameras is not None:
        count = int(cameras.world_to_camera.shape[0])
        pick = np.unique(np.linspace(0, count - 1, min(count, max_cameras)).round().astype(int))
        views = dict(viewmats=jnp.asarray(cameras.world_to_camera, jnp.float32)[pick],
                     Ks=jnp.asarray(cameras.K, jnp.float32)[pick], width=int(cameras.width),
                     height=int(cameras.height), margin=float(frustum_margin),
                     lenses=None if cameras.lens is None else jax.tree.map(lambda a: a[pick], cameras.lens))
    alive_rows = np.flatnonzero(np.asarray(anchors.alive))
    n = cfg.n_offsets
    chunk_anchors = max(1, min(int(chunk_anchors), len(alive_rows) or 1))
    parts = {key: [] for key in ("means", "quats", "scales", "opacities", "sh")}
    never = 0
    for start in range(0, len(alive_rows), chunk_anchors):
        rows = alive_rows[start:start + chunk_anchors]
        count = len(rows)
        index = np.concatenate([rows, np.full(chunk_anchors - count, rows[0])])  # one static shape: one compile
        valid = np.arange(chunk_anchors) < count
        params = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[index], anchors.params)
        baked = bake_anchors(nets["decoder"], params, jnp.asarray(anchors.centers)[index], jnp.asarray(valid),
                             appearance, jnp.asarray(dirs), jnp.asarray(fit), cfg, **views)
        baked = jax.tree_util.tree_map(np.asarray, baked)
        real = np.repeat(valid, n)
        keep = real & (baked.max_opacity > min_opacity)
        never += int(np.sum(real & ~keep))
        for key in parts:
            parts[key].append(getattr(baked, key)[keep])
        if progress is not None:
            progress(count)
    k = num_sh_coeffs(sh_degree)
    if alive_rows.size:
        cat = {key: np.concatenate(value) for key, value in parts.items()}
    else:
        cat = dict(means=np.zeros((0, 3)), quats=np.zeros((0, 4)), scales=np.ones((0, 3)), opacities=np.zeros(0),
                   sh=np.zeros((0, k, 3)))
    opacity = np.clip(cat["opacities"].astype(np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    model = SplatModel(
        means=cat["means"].astype(np.float32), quats=cat["quats"].astype(np.float32),
        log_scales=np.log(cat["scales"].astype(np.float64)).astype(np.float32),
        opacity_logits=(np.log(opacity) - np.log1p(-opacity)).astype(np.float32),
        sh=cat["sh"].astype(np.float32))
    summary = BakeSummary(gaussians=model.num_gaussians, considered=len(alive_rows) * n, dropped_never_visible=never,
                          sh_degree=sh_degree, directions=directions,
                          cameras=int(views["viewmats"].shape[0]) if views else 0)
    return model, summary
