"""Stage 1: quaternion + log-scale -> 3D covariance, forward and backward.

Spec: docs/spec/stages.md, clauses CNV-04, CNV-05, CNV-06, COV-01, COV-02.
Derivation of the backward: docs/derivations/covariance.md.

The stage's deviation options (docs/spec/deviations.md) are ``Profile.quat_order``,
``quat_normalization`` and ``rotation_transposed``; with ``profile=None`` or the reference values
the stage is exactly COV-01.
"""
from __future__ import annotations

import numpy as np

from .constants import QUAT_TINY_NORM

#: (w, x, y, z) taken from a quaternion stored (x, y, z, w): the "xyzw" reading of CNV-04
_XYZW_AS_WXYZ = [3, 0, 1, 2]


def normalize_quats(quats: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit quaternions from raw ones (CNV-05).

    quats (N, 4) (w, x, y, z), every row non-zero (``render`` validates this).
    Every row is first divided by its largest |component| (exact up to one rounding, and immune
    to underflow of |q|**2 for tiny or subnormal q and to overflow for huge q, in either dtype),
    then normalised.  Returns ``(q_unit (N,4), norm (N,), maxabs (N,))`` with ``norm`` = |q|
    (computed as |q / maxabs| * maxabs), used by the backward.
    """
    q = np.asarray(quats)
    a = np.abs(q)
    # max and sum over the four components written out column by column: the same values as
    # np.max / np.sum along axis -1 (the sum in the same order), without numpy's slow reductions
    # along a length-4 axis (5x faster at 128k rows)
    maxabs = np.maximum(np.maximum(a[:, 0], a[:, 1]), np.maximum(a[:, 2], a[:, 3]))
    safe = np.where(maxabs > 0, maxabs, 1).astype(q.dtype)
    qs = q / safe[:, None]
    ns = np.sqrt(qs[:, 0] * qs[:, 0] + qs[:, 1] * qs[:, 1] + qs[:, 2] * qs[:, 2] + qs[:, 3] * qs[:, 3])
    return qs / ns[:, None], ns * safe, safe


def quat_to_rotmat(q_unit: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) from unit quaternions (N, 4) (w, x, y, z) (CNV-04)."""
    q = np.asarray(q_unit)
    w, x, y, z = np.ascontiguousarray(np.moveaxis(q, -1, 0))    # components as contiguous rows
    rows = np.empty((9,) + q.shape[:-1], dtype=q.dtype)         # R's entries, row-major
    rows[0] = 1 - 2 * (y * y + z * z)
    rows[1] = 2 * (x * y - w * z)
    rows[2] = 2 * (x * z + w * y)
    rows[3] = 2 * (x * y + w * z)
    rows[4] = 1 - 2 * (x * x + z * z)
    rows[5] = 2 * (y * z - w * x)
    rows[6] = 2 * (x * z - w * y)
    rows[7] = 2 * (y * z + w * x)
    rows[8] = 1 - 2 * (x * x + y * y)
    return np.ascontiguousarray(np.moveaxis(rows, 0, -1)).reshape(q.shape[:-1] + (3, 3))


def covariance_3d(quats: np.ndarray, log_scales: np.ndarray, profile=None) -> dict:
    """Sigma = R S S^T R^T with S = diag(exp(log_scales)), R from the normalised quaternion (COV-01).

    quats (N, 4), log_scales (N, 3), profile: a refgs.Profile whose deviation options apply, or
    None (the reference)  ->  dict with
      ``cov3d`` (N, 3, 3) symmetric, ``R`` (N, 3, 3), ``scales`` (N, 3), ``q_unit`` (N, 4),
      ``q_norm`` (N,) -- the last four are what the backward needs -- and ``options``.
    """
    order, norm, transposed = ("wxyz", "exact", False) if profile is None else (
        profile.quat_order, profile.quat_normalization, profile.rotation_transposed)
    q = quats[:, _XYZW_AS_WXYZ] if order == "xyzw" else quats     # deviation quat_xyzw
    q_unit, q_norm, _ = normalize_quats(q)
    if norm == "none":                              # deviation quat_unnormalised
        q_unit, q_norm = q, np.ones_like(q_norm)
    elif norm == "eps":                             # deviation quat_normalize_eps
        q_unit = np.where((q_norm < QUAT_TINY_NORM)[:, None], q / q.dtype.type(QUAT_TINY_NORM), q_unit)
    R = quat_to_rotmat(q_unit)
    if transposed:                                  # deviation rotation_transposed
        R = np.swapaxes(R, -1, -2)
    scales = np.exp(log_scales)
    M = R * scales[:, None, :]                      # M = R S (columns scaled)
    cov = M @ np.swapaxes(M, -1, -2)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))    # exact symmetry
    return {"cov3d": cov, "R": R, "scales": scales, "q_unit": q_unit, "q_norm": q_norm,
            "options": (order, norm, transposed)}


def rotmat_to_quat_vjp(q_unit: np.ndarray, v_R: np.ndarray) -> np.ndarray:
    """dL/dq_unit (N, 4) from dL/dR (N, 3, 3) through ``quat_to_rotmat`` (COV-02)."""
    w, x, y, z = (q_unit[:, i] for i in range(4))
    g = v_R
    v_w = 2 * (-z * g[:, 0, 1] + y * g[:, 0, 2] + z * g[:, 1, 0] - x * g[:, 1, 2]
               - y * g[:, 2, 0] + x * g[:, 2, 1])
    v_x = 2 * (y * g[:, 0, 1] + z * g[:, 0, 2] + y * g[:, 1, 0] - 2 * x * g[:, 1, 1]
               - w * g[:, 1, 2] + z * g[:, 2, 0] + w * g[:, 2, 1] - 2 * x * g[:, 2, 2])
    v_y = 2 * (-2 * y * g[:, 0, 0] + x * g[:, 0, 1] + w * g[:, 0, 2] + x * g[:, 1, 0]
               + z * g[:, 1, 2] - w * g[:, 2, 0] + z * g[:, 2, 1] - 2 * y * g[:, 2, 2])
    v_z = 2 * (-2 * z * g[:, 0, 0] - w * g[:, 0, 1] + x * g[:, 0, 2] + w * g[:, 1, 0]
               - 2 * z * g[:, 1, 1] + y * g[:, 1, 2] + x * g[:, 2, 0] + y * g[:, 2, 1])
    return np.stack([v_w, v_x, v_y, v_z], axis=-1)


def normalize_quats_vjp(q_unit: np.ndarray, q_norm: np.ndarray, v_q_unit: np.ndarray) -> np.ndarray:
    """dL/dq from dL/d(q/|q|): (I - u u^T) v / |q| (COV-02)."""
    proj = v_q_unit - q_unit * np.sum(q_unit * v_q_unit, axis=-1, keepdims=True)
    return proj / q_norm[:, None]


def covariance_3d_backward(fwd: dict, v_cov3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Backward of :func:`covariance_3d` (COV-02).

    fwd      the dict returned by the forward
    v_cov3d  (N, 3, 3) dL/dSigma, entries treated as independent (any matrix; only its symmetric
             part matters because Sigma is symmetric)
    returns  (v_quats (N, 4), v_log_scales (N, 3))
    """
    R, s = fwd["R"], fwd["scales"]
    order, norm, transposed = fwd.get("options", ("wxyz", "exact", False))
    M = R * s[:, None, :]
    v_M = (v_cov3d + np.swapaxes(v_cov3d, -1, -2)) @ M   # Sigma = M M^T
    v_R = v_M * s[:, None, :]                           # M = R diag(s)
    v_s = np.sum(v_M * R, axis=-2)
    v_log_scales = v_s * s                              # s = exp(log s)
    if transposed:                                      # deviation rotation_transposed
        v_R = np.swapaxes(v_R, -1, -2)
    v_q_unit = rotmat_to_quat_vjp(fwd["q_unit"], v_R)
    if norm == "none":                                  # deviation quat_unnormalised
        v_quats = v_q_unit
    else:
        v_quats = normalize_quats_vjp(fwd["q_unit"], fwd["q_norm"], v_q_unit)
        if norm == "eps":                               # deviation quat_normalize_eps
            tiny = (fwd["q_norm"] < QUAT_TINY_NORM)[:, None]
            v_quats = np.where(tiny, v_q_unit / v_q_unit.dtype.type(QUAT_TINY_NORM), v_quats)
    if order == "xyzw":                                 # deviation quat_xyzw
        v_stored = np.empty_like(v_quats)
        v_stored[:, _XYZW_AS_WXYZ] = v_quats
        v_quats = v_stored
    return v_quats, v_log_scales
