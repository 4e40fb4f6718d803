"""The standard 3DGS PLY (docs/formats.md#standard-3dgs-ply): what every viewer reads, in and out.

Layout (graphdeco ``scene/gaussian_model.py`` ``save_ply``): binary
little-endian, one ``vertex`` element, float32 properties in the order
``x y z nx ny nz f_dc_0..2 f_rest_0..(3(K−1)−1) opacity scale_0..2 rot_0..3``.
``f_rest`` is channel-major (every R coefficient 1…K−1, then G, then B: graphdeco
stores ``features_rest`` [G, K−1, 3] transposed to [G, 3, K−1] and flattened).
``opacity`` is a logit, ``scale_*`` are log σ, ``rot_*`` a wxyz quaternion as
stored (unnormalised). Normals are written as zeros.

Reading looks every property up by name, so files in another property order,
without normals, in ASCII or big-endian, or with float64 properties load too;
the SH degree follows from the ``f_rest`` count. Every problem raises
:class:`PlyError` naming the file.

Naming (:mod:`cusgs_jax.types`): G Gaussians, K = (d+1)² SH coefficients per channel.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import re

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from cusgs_jax.errors import UserError
from cusgs_jax.model.splats import SplatModel  # noqa: F401 (the PLY's model type, re-exported here)
from cusgs_jax.atomic import atomic_path

__all__ = ["PlyError", "SplatModel", "read_ply", "write_ply", "ply_property_names"]

_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")


class PlyError(UserError):
    """A PLY file that cannot be read or written as a standard 3DGS PLY (file named in the message)."""


def ply_property_names(sh_degree: int, normals: bool = True) -> list[str]:
    """The standard property order for SH degree d (docs/formats.md#standard-3dgs-ply, graphdeco ``construct_list_of_attributes``)."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(rest)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
            + [f"rot_{i}" for i in range(4)])


def _host(model: SplatModel, path) -> dict[str, np.ndarray]:
    """The model's arrays as float32 NumPy, shapes checked."""
    arrays = {f.name: np.asarray(getattr(model, f.name), np.float32) for f in dataclasses.fields(SplatModel)}
    g = arrays["means"].shape[0] if arrays["means"].ndim == 2 else -1
    k = arrays["sh"].shape[1] if arrays["sh"].ndim == 3 else -1
    want = dict(means=((g, 3), "[G, 3]"), quats=((g, 4), "[G, 4]"), log_scales=((g, 3), "[G, 3]"),
                opacity_logits=((g,), "[G]"), sh=((g, k, 3), "[G, K, 3]"))
    for name, (shape, text) in want.items():
        if arrays[name].shape != shape or g < 1:
            raise PlyError(f"cannot write {path}: {name} has shape {arrays[name].shape}, expected {text} "
                           f"with the same G ≥ 1 Gaussians as means {arrays['means'].shape}")
    if k not in (1, 4, 9, 16):
        raise PlyError(f"cannot write {path}: sh has K = {k} coefficients per channel, expected 1, 4, 9 or 16 "
                       "(SH degree 0–3)")
    for name, a in arrays.items():
        bad = int(np.count_nonzero(~np.isfinite(a)))
        if bad:
            raise PlyError(f"cannot write {path}: {name} has {bad} non-finite values (NaN or Inf)")
    return arrays


def write_ply(path: str | os.PathLike, gaussians: SplatModel) -> pathlib.Path:
    """Write ``gaussians`` as a standard 3DGS PLY (binary little-endian float32, docs/formats.md#standard-3dgs-ply).

    Returns the path written. Raises PlyError for bad shapes, non-finite values or
    a file that cannot be written.
    """
    path = pathlib.Path(path)
    a = _host(gaussians, path)
    g, k = a["sh"].shape[:2]
    names = ply_property_names((round(k ** 0.5)) - 1)
    columns = np.concatenate([
        a["means"], np.zeros((g, 3), np.float32), a["sh"][:, 0, :],
        a["sh"][:, 1:, :].transpose(0, 2, 1).reshape(g, 3 * (k - 1)),  # channel-major f_rest (save_ply)
        a["opacity_logits"][:, None], a["log_scales"], a["quats"]], axis=1)
    assert columns.shape[1] == len(names)
    vertex = np.empty(g, dtype=[(n, "<f4") for n in names])
    for i, n in enumerate(names):
        vertex[n] = columns[:, i]
    try:
        with atomic_path(path) as tmp:  # whole or absent, even if the process is killed mid-write
            PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(tmp))
    except OSError as e:
        raise PlyError(f"cannot write {path}: {e.strerror or e}") from e
    return path


def read_ply(path: str | os.PathLike) -> SplatModel:
    """Read a standard 3DGS PLY into a :class:`SplatModel` (NumPy float32 arrays, values as stored).

    Properties are found by name (any order; normals optional); the SH degree is
    inferred from the number of ``f_rest_*`` properties, which must be
    3·((d+1)² − 1) for some d ≥ 0 and numbered 0… without gaps.

    An infinite ``opacity`` logit (opacity exactly 1 or 0) is read as ±:data:`OPACITY_LOGIT_LIMIT`.

    Raises:
      PlyError: the file is missing, not a PLY, has no ``vertex`` element or no
        vertices, lacks a property, has a wrong ``f_rest`` count, or holds
        NaN or (outside ``opacity``) infinite values — the message names the file and the problem.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise PlyError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        with open(path, "rb") as f:
            ply = PlyData.read(f)
            columns = _read_columns(ply, path)
    except PlyError:
        raise
    except PlyParseError as e:
        raise PlyError(f"{path}: not a readable PLY file ({e})") from e
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise PlyError(f"{path}: cannot read it as a PLY file ({e})") from e

    g = columns["x"].shape[0]
    rest = sorted((int(m.group(1)), n) for n in columns if (m := re.fullmatch(r"f_rest_(\d+)", n)))
    k = _sh_coeffs(len(rest), path)
    if [i for i, _ in rest] != list(range(len(rest))):
        raise PlyError(f"{path}: f_rest properties are not numbered f_rest_0..f_rest_{len(rest) - 1}")

    def stack(names):
        return np.stack([columns[n] for n in names], axis=1)

    sh = np.empty((g, k, 3), np.float32)
    sh[:, 0, :] = stack(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:  # channel-major f_rest: index c·(K−1) + (k−1)
        sh[:, 1:, :] = stack([n for _, n in rest]).reshape(g, 3, k - 1).transpose(0, 2, 1)
    return SplatModel(means=stack(["x", "y", "z"]), quats=stack([f"rot_{i}" for i in range(4)]),
                      log_scales=stack([f"scale_{i}" for i in range(3)]),
                      opacity_logits=columns["opacity"].copy(), sh=sh)


def _read_columns(ply, path: pathlib.Path) -> dict[str, np.ndarray]:
    """Every scalar property of the ``vertex`` element as a float32 copy (checked: present, finite)."""
    if "vertex" not in [e.name for e in ply.elements]:
        found = ", ".join(e.name for e in ply.elements) or "none"
        raise PlyError(f"{path}: no 'vertex' element (elements: {found}); a 3DGS PLY stores one vertex per Gaussian")
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise PlyError(f"{path}: missing vertex properties {', '.join(missing)} (a standard 3DGS PLY has "
                       "x y z f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3)")
    if len(vertex.data) == 0:
        raise PlyError(f"{path}: the vertex element is empty (no Gaussians)")
    wanted = [n for n in names if n in _REQUIRED or n.startswith("f_rest_")]
    columns = {}
    for n in wanted:
        data = vertex.data[n]
        if data.dtype == object:
            raise PlyError(f"{path}: vertex property {n} is a list, expected a scalar")
        columns[n] = np.array(data, dtype=np.float32)  # a copy in native order, never the file's memory map
        if n == "opacity":  # ±inf logits: opacity exactly 1 or 0, as converters write 8-bit alpha 255 / 0
            columns[n] = np.where(np.isinf(columns[n]), np.sign(columns[n]) * OPACITY_LOGIT_LIMIT, columns[n])
        bad = int(np.count_nonzero(~np.isfinite(columns[n])))
        if bad:
            raise PlyError(f"{path}: vertex property {n} has {bad} non-finite values (NaN or Inf)")
    return columns


OPACITY_LOGIT_LIMIT = 30.0
"""An infinite opacity logit read from a file becomes ±30: sigmoid(30) is 1 in float32 and
sigmoid(−30) ≈ 1e−13 (PlayCanvas ``splat-transform`` writes ±inf for the 8-bit alpha 255 / 0 of
an SPZ or compressed PLY it converts back; measured on a round trip of a refined export)."""


def _sh_coeffs(num_rest: int, path: pathlib.Path) -> int:
    """K from the f_rest count 3·(K − 1), K = (d+1)²; PlyError otherwise."""
    if num_rest % 3 == 0:
        k = num_rest // 3 + 1
        d = round(k ** 0.5) - 1
        if (d + 1) ** 2 == k:
            return k
    valid = ", ".join(f"{3 * ((d + 1) ** 2 - 1)} (degree {d})" for d in range(4))
    raise PlyError(f"{path}: {num_rest} f_rest properties is not 3·((d+1)²−1) for an SH degree d; "
                   f"expected e.g. {valid}")
