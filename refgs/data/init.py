"""Gaussians from a point cloud, as 3DGS ``GaussianModel.create_from_pcd`` (clauses DAT-13, DAT-14).

Source: graphdeco-inria/gaussian-splatting@82bc469 scene/gaussian_model.py create_from_pcd and
submodules/simple-knn/simple_knn.cu (peers.md 1.8).  One difference: simple-knn's nearest
neighbours are approximate (Morton-order boxes); here they are exact (scipy cKDTree).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..constants import SH_C0, SH_COLOR_OFFSET
from ..errors import ConfigError
from ..types import Gaussians

#: Initial opacity of every Gaussian (create_from_pcd: ``inverse_sigmoid(0.1 * ones)``).  [DAT-13]
INIT_OPACITY = 0.1

#: Floor on the mean squared neighbour distance (create_from_pcd:
#: ``torch.clamp_min(distCUDA2(...), 0.0000001)``); smallest log-scale ln(sqrt(1e-7)) = -8.06.
#: [DAT-14]
MIN_DIST2 = 1e-7

#: Neighbours averaged (simple_knn.cu boxMeanDist: ``(best[0] + best[1] + best[2]) / 3``).  [DAT-14]
KNN_NEIGHBOURS = 3


def knn_log_scales(points) -> np.ndarray:
    """Per-point log-scale: ``log(sqrt(max(mean_k d_k^2, MIN_DIST2)))`` over the K=3 nearest
    other points (clause DAT-14).  points (P, 3) -> (P,) float64.

    Fewer than 4 points: the mean runs over the P - 1 neighbours that exist; a single point
    (no neighbour) gets the floor MIN_DIST2.  Coincident points give distance 0 -> the floor.
    (simple-knn fills missing neighbours with FLT_MAX; we choose the finite rule.)
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n <= 1:
        return np.full(n, 0.5 * np.log(MIN_DIST2))
    if not np.all(np.isfinite(pts)):
        raise ConfigError("init points: coordinates must be finite")
    k = min(KNN_NEIGHBOURS, n - 1)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)  # column 0 is the point itself
    dist2 = np.mean(np.asarray(dist).reshape(n, k + 1)[:, 1:] ** 2, axis=1)
    return 0.5 * np.log(np.maximum(dist2, MIN_DIST2))


def init_gaussians_from_points(points, colors, sh_degree: int = 3, dtype=np.float64) -> Gaussians:
    """Gaussians at ``points`` (P, 3) with ``colors`` (P, 3) in [0, 1] (clause DAT-13).

    sh (P, (d+1)^2, 3): DC = (rgb - 0.5) / SH_C0, rest 0;  quats (1, 0, 0, 0);
    opacity_logits logit(INIT_OPACITY);  log_scales knn_log_scales repeated on 3 axes (DAT-14).
    """
    pts = np.asarray(points, dtype=np.float64)
    rgb = np.asarray(colors, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ConfigError(f"init points: expected shape (P, 3), got {pts.shape}")
    if rgb.shape != pts.shape:
        raise ConfigError(f"init colours: expected shape {pts.shape} like the points, "
                          f"got {rgb.shape}")
    if not (np.all(np.isfinite(rgb)) and rgb.min(initial=0.0) >= 0 and rgb.max(initial=0.0) <= 1):
        raise ConfigError("init colours: expected values in [0, 1] (divide 8-bit colours by 255)")
    if not (isinstance(sh_degree, (int, np.integer)) and 0 <= sh_degree <= 3):
        raise ConfigError(f"--sh-degree: expected an integer in 0..3, got {sh_degree!r}")
    n = len(pts)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0, :] = (rgb - SH_COLOR_OFFSET) / SH_C0
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    logit = np.log(INIT_OPACITY / (1.0 - INIT_OPACITY))
    log_scales = np.repeat(knn_log_scales(pts)[:, None], 3, axis=1)
    return Gaussians(pts, log_scales, quats, np.full(n, logit), sh).astype(dtype)


__all__ = ["init_gaussians_from_points", "knn_log_scales", "INIT_OPACITY", "MIN_DIST2",
           "KNN_NEIGHBOURS"]
