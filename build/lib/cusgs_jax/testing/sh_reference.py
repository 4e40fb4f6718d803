"""Float64 NumPy spherical harmonics → RGB: the oracle of :mod:`cusgs_jax.splat.sh`.

Written independently of ``splat/sh.py``: every term is the closed-form real
spherical harmonic of the table (``√(·/π)`` factors, not the decimal
constants), with the signs graphdeco's ``eval_sh`` gives each term. No JAX.

Naming (:mod:`cusgs_jax.types`): K = (d+1)² coefficients per channel.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["sh_basis_reference", "sh_to_rgb_reference", "sh_constants_reference"]

_PI = math.pi


def sh_constants_reference() -> dict:
    """Closed forms of eval_sh's constants: {"C0": float, "C1": float, "C2": [5], "C3": [7]}."""
    return dict(
        C0=0.5 * math.sqrt(1.0 / _PI),
        C1=math.sqrt(3.0 / (4.0 * _PI)),
        C2=[0.5 * math.sqrt(15.0 / _PI), -0.5 * math.sqrt(15.0 / _PI), 0.25 * math.sqrt(5.0 / _PI),
            -0.5 * math.sqrt(15.0 / _PI), 0.25 * math.sqrt(15.0 / _PI)],
        C3=[-0.25 * math.sqrt(35.0 / (2.0 * _PI)), 0.5 * math.sqrt(105.0 / _PI),
            -0.25 * math.sqrt(21.0 / (2.0 * _PI)), 0.25 * math.sqrt(7.0 / _PI),
            -0.25 * math.sqrt(21.0 / (2.0 * _PI)), 0.25 * math.sqrt(105.0 / _PI),
            -0.25 * math.sqrt(35.0 / (2.0 * _PI))],
    )


def sh_basis_reference(dirs, degree: int) -> np.ndarray:
    """[..., K] float64 basis values at ``dirs`` [..., 3] (normalised here), K = (degree+1)²."""
    d = np.asarray(dirs, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    c = sh_constants_reference()
    terms = [np.full(x.shape, c["C0"])]                        # l = 0
    if degree >= 1:                                            # l = 1: m = -1, 0, 1
        terms.append(-c["C1"] * y)
        terms.append(c["C1"] * z)
        terms.append(-c["C1"] * x)
    if degree >= 2:                                            # l = 2: m = -2 … 2
        terms.append(c["C2"][0] * x * y)
        terms.append(c["C2"][1] * y * z)
        terms.append(c["C2"][2] * (3.0 * z * z - 1.0))         # = 2z² − x² − y² on the sphere
        terms.append(c["C2"][3] * x * z)
        terms.append(c["C2"][4] * (x * x - y * y))
    if degree >= 3:                                            # l = 3: m = -3 … 3
        terms.append(c["C3"][0] * y * (3.0 * x * x - y * y))
        terms.append(c["C3"][1] * x * y * z)
        terms.append(c["C3"][2] * y * (5.0 * z * z - 1.0))     # = 4z² − x² − y²
        terms.append(c["C3"][3] * z * (5.0 * z * z - 3.0))     # = 2z² − 3x² − 3y²
        terms.append(c["C3"][4] * x * (5.0 * z * z - 1.0))
        terms.append(c["C3"][5] * z * (x * x - y * y))
        terms.append(c["C3"][6] * x * (x * x - 3.0 * y * y))
    if degree > 3:
        raise ValueError("the reference covers degrees 0–3")
    return np.stack(terms, axis=-1)


def sh_to_rgb_reference(coeffs, dirs) -> np.ndarray:
    """``max(0, 0.5 + Σ_k c_k Y_k(dir))``: coeffs [..., K, 3], dirs [..., 3] → [..., 3] float64.

    A loop over coefficients and channels, one term at a time.
    """
    coeffs = np.asarray(coeffs, np.float64)
    num = coeffs.shape[-2]
    degree = int(round(math.sqrt(num))) - 1
    assert (degree + 1) ** 2 == num, num
    basis = sh_basis_reference(dirs, degree)
    shape = np.broadcast_shapes(basis.shape[:-1], coeffs.shape[:-2])
    rgb = np.full(shape + (3,), 0.5)
    for channel in range(3):
        for k in range(num):
            rgb[..., channel] += coeffs[..., k, channel] * basis[..., k]
    return np.maximum(rgb, 0.0)
