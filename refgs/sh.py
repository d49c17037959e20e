"""Stage 3: view-dependent colour from real spherical harmonics of degree 0..3.

Spec: docs/spec/conventions.md CNV-09, CNV-10; docs/spec/stages.md SH-01..SH-04.
Derivation of the backward: docs/derivations/sh.md.
"""
from __future__ import annotations

import numpy as np

from .constants import SH_C0, SH_C1, SH_C2, SH_C3, SH_COLOR_OFFSET, SH_MAX_DEGREE


def num_sh_coeffs(degree: int) -> int:
    """(degree + 1)**2 coefficients per channel (SH-01)."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Basis values and their derivatives w.r.t. the unit direction (CNV-09, SH-02).

    dirs (N,3) unit vectors (x, y, z)  ->  (basis (N, B), dbasis (N, B, 3)), B = (degree+1)**2.
    The order and signs are those of the original 3DGS (auxiliary.h:21-39, forward.cu:20-71).
    """
    if not 0 <= degree <= SH_MAX_DEGREE:
        raise ValueError(f"RenderConfig.sh_degree: expected 0..{SH_MAX_DEGREE}, got {degree}")
    n = dirs.shape[0]
    dt = dirs.dtype
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    one, zero = np.ones(n, dt), np.zeros(n, dt)
    B = [SH_C0 * one]
    dB = [(zero, zero, zero)]                       # (d/dx, d/dy, d/dz)
    if degree >= 1:
        B += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
        dB += [(zero, -SH_C1 * one, zero), (zero, zero, SH_C1 * one), (-SH_C1 * one, zero, zero)]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        c = SH_C2
        B += [c[0] * x * y, c[1] * y * z, c[2] * (2 * zz - xx - yy), c[3] * x * z, c[4] * (xx - yy)]
        dB += [(c[0] * y, c[0] * x, zero),
               (zero, c[1] * z, c[1] * y),
               (-2 * c[2] * x, -2 * c[2] * y, 4 * c[2] * z),
               (c[3] * z, zero, c[3] * x),
               (2 * c[4] * x, -2 * c[4] * y, zero)]
    if degree >= 3:
        c = SH_C3
        B += [c[0] * y * (3 * xx - yy),
              c[1] * x * y * z,
              c[2] * y * (4 * zz - xx - yy),
              c[3] * z * (2 * zz - 3 * xx - 3 * yy),
              c[4] * x * (4 * zz - xx - yy),
              c[5] * z * (xx - yy),
              c[6] * x * (xx - 3 * yy)]
        dB += [(c[0] * 6 * x * y, c[0] * (3 * xx - 3 * yy), zero),
               (c[1] * y * z, c[1] * x * z, c[1] * x * y),
               (-2 * c[2] * x * y, c[2] * (4 * zz - xx - 3 * yy), 8 * c[2] * y * z),
               (-6 * c[3] * x * z, -6 * c[3] * y * z, c[3] * (6 * zz - 3 * xx - 3 * yy)),
               (c[4] * (4 * zz - 3 * xx - yy), -2 * c[4] * x * y, 8 * c[4] * x * z),
               (2 * c[5] * x * z, -2 * c[5] * y * z, c[5] * (xx - yy)),
               (c[6] * (3 * xx - 3 * yy), -6 * c[6] * x * y, zero)]
    basis = np.stack(B, axis=-1).astype(dt, copy=False)
    dbasis = np.stack([np.stack(d, axis=-1) for d in dB], axis=1).astype(dt, copy=False)
    return basis, dbasis


def eval_sh_colors(means: np.ndarray, sh: np.ndarray, campos: np.ndarray, degree: int,
                   profile=None) -> dict:
    """Colours of N Gaussians seen from ``campos`` (SH-01..SH-03, CNV-10).

    means (N,3), sh (N,K,3) with K >= (degree+1)**2 (extra coefficients ignored), campos (3,);
    profile: a refgs.Profile whose deviation options (``sh_dir_reversed``, ``colour_max``) apply,
    or None (the reference).
    dir = normalize(mean - campos); rgb = sum_k basis_k sh_k + 0.5; colors = max(rgb, 0).
    Returns a dict with ``colors`` (N,3), ``clamped`` (N,3) bool (rgb < 0), and the intermediates
    (``dirs``, ``dist``, ``basis``, ``dbasis``) that the backward needs.
    """
    nb = num_sh_coeffs(degree)
    if sh.shape[1] < nb:
        raise ValueError(f"Gaussians.sh: degree {degree} needs K >= {nb} coefficients, got K = {sh.shape[1]}")
    reversed_dir = profile is not None and profile.sh_dir_reversed
    if reversed_dir:                                # deviation sh_dir_reversed
        d = np.asarray(campos, dtype=means.dtype) - means
    else:
        d = means - np.asarray(campos, dtype=means.dtype)
    dist = np.sqrt(np.sum(d * d, axis=-1))
    dist_safe = np.where(dist > 0, dist, 1)
    dirs = d / dist_safe[:, None]
    basis, dbasis = sh_basis(degree, dirs)
    rgb = np.einsum("nk,nkc->nc", basis, sh[:, :nb, :]) + means.dtype.type(SH_COLOR_OFFSET)
    clamped = rgb < 0
    colors = np.where(clamped, means.dtype.type(0), rgb)
    if profile is not None and profile.colour_max < np.inf:      # deviation colour_clamp_01
        over = rgb > profile.colour_max
        colors = np.where(over, means.dtype.type(profile.colour_max), colors)
        clamped = clamped | over
    return {"colors": colors, "clamped": clamped, "dirs": dirs, "dist": dist_safe,
            "basis": basis, "dbasis": dbasis, "degree": degree, "dir_sign": -1 if reversed_dir else 1}


def eval_sh_colors_backward(fwd: dict, sh: np.ndarray, v_colors: np.ndarray):
    """Backward of :func:`eval_sh_colors` (SH-04).

    v_colors (N,3)  ->  (v_sh (N,K,3) zero above the active degree, v_means (N,3) through the
    view direction).  Channels clamped in the forward (rgb < 0) pass no gradient.
    """
    nb = fwd["basis"].shape[1]
    g = np.where(fwd["clamped"], 0, v_colors)
    v_sh = np.zeros_like(sh)
    v_sh[:, :nb, :] = fwd["basis"][:, :, None] * g[:, None, :]
    # d rgb_c / d dir = sum_k dbasis_k sh_kc
    v_basis = np.einsum("nkc,nc->nk", sh[:, :nb, :], g)
    v_dir = np.einsum("nk,nkj->nj", v_basis, fwd["dbasis"])
    dirs = fwd["dirs"]
    # dir = d / |d|: v_d = (v_dir - dir (dir . v_dir)) / |d|
    v_d = (v_dir - dirs * np.sum(dirs * v_dir, axis=-1, keepdims=True)) / fwd["dist"][:, None]
    if fwd.get("dir_sign", 1) < 0:                  # deviation sh_dir_reversed: d = campos - mean
        v_d = -v_d
    return v_sh, v_d
