"""Niantic's SPZ (gzip-compressed, quantised 3DGS) in and out, through the optional ``gsply`` package.

SPZ (github.com/nianticlabs/spz) stores what the standard PLY stores, quantised: positions as
24-bit fixed point with ``fractional_bits`` fractional bits, opacity as 8-bit alpha, the SH DC term,
log-scales and the higher SH coefficients as 8 bits each, rotations as "smallest three" (version 3),
the whole payload gzipped — about a tenth of the PLY. The encoder and decoder are ``gsply``'s
(OpsiClear, MIT, on PyPI; ``pip install 'cusgs-jax[spz]'``); it is imported only when an SPZ is
read or written, so the project runs without it.

Coordinates are written as they are (the PLY's frame, as Niantic's own PLY → SPZ converter and
PlayCanvas ``splat-transform`` do): nothing is flipped. ``fractional_bits`` is 12 (Niantic's
default, 1/4096 of a unit) unless a coordinate is too large for 24 bits at that precision; it is
then lowered until every position fits (readers take it from the file's header).

Naming (:mod:`cusgs_jax.types`): G Gaussians, K = (d+1)² SH coefficients.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from cusgs_jax.errors import UserError
from cusgs_jax.atomic import atomic_path
from cusgs_jax.io.ply import SplatModel

__all__ = ["write_spz", "read_spz", "spz_fractional_bits", "require_gsply", "SPZ_INSTALL_HINT"]

SPZ_INSTALL_HINT = "pip install 'cusgs-jax[spz]' (or pip install gsply)"
DEFAULT_FRACTIONAL_BITS = 12  # Niantic's writer default: positions to 1/4096 of a unit
_POSITION_BITS = 24  # signed fixed point: |x| · 2^bits < 2^23


def require_gsply(path):
    """The ``gsply`` module, or a UserError naming ``path`` and how to install it (check before long work)."""
    try:
        import gsply  # optional dependency (the spz extra): imported only when an SPZ is read or written
    except ImportError as e:
        raise UserError(f"{path}: reading or writing SPZ needs the optional gsply package ({e}); install it with "
                        f"{SPZ_INSTALL_HINT}, or write a .ply") from e
    return gsply


def spz_fractional_bits(means) -> int:
    """Fractional bits (1–12) for positions [G, 3]: 12 when every ``|x| < 2^11``, fewer for larger coordinates.

    Raises:
      ValueError: a non-finite position, or one too far out even at 1 fractional bit (|x| ≥ 2^22).
    """
    means = np.asarray(means, np.float64)
    if means.size and not np.all(np.isfinite(means)):
        raise ValueError("SPZ cannot store a non-finite position")
    largest = float(np.max(np.abs(means))) if means.size else 0.0
    limit = _POSITION_BITS - 1  # bits for |x| · 2^bits, sign excluded
    bits = DEFAULT_FRACTIONAL_BITS if largest == 0.0 else min(DEFAULT_FRACTIONAL_BITS,
                                                            limit - 1 - math.floor(math.log2(largest)))
    if bits < 1:
        raise ValueError(f"a position of magnitude {largest:g} is too large for SPZ's 24-bit fixed point")
    return bits


def write_spz(path, model: SplatModel) -> pathlib.Path:
    """Write ``model`` (G Gaussians, SH degree 0–3) to ``path`` as SPZ version 3 (gzip container).

    The opacity logits, log-scales, unit wxyz quaternions, SH DC and higher SH coefficients
    are quantised as SPZ stores them (``gsply.write_spz``); positions keep
    :func:`spz_fractional_bits` fractional bits.

    Returns:
      The path written.
    Raises:
      UserError: ``gsply`` is not installed, a position SPZ cannot store, or the file cannot be written.
    """
    path = pathlib.Path(path)
    gsply = require_gsply(path)
    means = np.asarray(model.means, np.float32)
    try:
        bits = spz_fractional_bits(means)
    except ValueError as e:
        raise UserError(f"{path}: {e}; write a .ply instead") from e
    quats = np.asarray(model.quats, np.float64)
    quats = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    sh = np.asarray(model.sh, np.float32)
    data = gsply.GSData(means=means, scales=np.asarray(model.log_scales, np.float32),
                        quats=quats.astype(np.float32), opacities=np.asarray(model.opacity_logits, np.float32),
                        sh0=np.ascontiguousarray(sh[:, 0, :]), shN=np.ascontiguousarray(sh[:, 1:, :]))
    try:
        with atomic_path(path) as tmp:  # whole or absent, even if the process is killed mid-write
            gsply.write_spz(tmp, data, version=3, fractional_bits=bits)
    except OSError as e:
        raise UserError(f"cannot write {path} ({e.strerror or e}); pass a writable path") from e
    return path


def read_spz(path) -> SplatModel:
    """Read an SPZ file (any version ``gsply`` reads) into a :class:`SplatModel` (float32).

    Returns:
      G Gaussians: means [G, 3], unit wxyz quats [G, 4], log_scales [G, 3], opacity_logits [G]
      (±inf where the 8-bit alpha is 255 / 0, clipped to ±30 as :func:`~cusgs_jax.io.read_ply` does),
      sh [G, K, 3].
    Raises:
      UserError: ``gsply`` is not installed, or the file is missing or not an SPZ.
    """
    path = pathlib.Path(path)
    gsply = require_gsply(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file (pass an .spz file)")
    try:
        data = gsply.read_spz(path)
    except (ValueError, OSError, EOFError) as e:
        raise UserError(f"{path}: not a readable SPZ file ({e})") from e
    sh0 = np.asarray(data.sh0, np.float32)[:, None, :]
    rest = np.asarray(data.shN, np.float32) if data.shN is not None else np.zeros((len(sh0), 0, 3), np.float32)
    rest = rest.reshape(len(sh0), -1, 3)
    logits = np.clip(np.nan_to_num(np.asarray(data.opacities, np.float32), posinf=30.0, neginf=-30.0), -30.0, 30.0)
    return SplatModel(means=np.asarray(data.means, np.float32), quats=np.asarray(data.quats, np.float32),
                      log_scales=np.asarray(data.scales, np.float32), opacity_logits=logits,
                      sh=np.concatenate([sh0, rest], axis=1))
