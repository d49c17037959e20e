"""Learning rates and schedules of 3DGS training (clauses TRN-02, TRN-03).

Sources: graphdeco-inria/gaussian-splatting@82bc469 ``arguments/__init__.py`` (OptimizationParams)
and ``scene/gaussian_model.py training_setup`` / ``update_learning_rate``; ``utils/general_utils.py``
@15d64e6 ``get_expon_lr_func``; DCVL-3D/DropGaussian_release@c13da4a ``arguments/__init__.py``
L75-91 (peers.md 1.6, 3.1).  Iterations are counted from 1, as in 3DGS' ``train.py``.

Rule for horizons: every schedule with a horizon uses T = the run's iteration count (--iters);
fixed intervals (SH every 1000, densify every 100, opacity reset every 3000) stay fixed in
iterations whatever T is.
"""
from __future__ import annotations

import math

import numpy as np

#: Position lr at t = 0, times the scene extent (``position_lr_init``).  [TRN-02]
POSITION_LR_INIT = 1.6e-4
#: Position lr at t = T, times the scene extent (``position_lr_final``; the final value is also
#: multiplied by ``spatial_lr_scale``, peers.md 1.6 NOTE).  [TRN-02]
POSITION_LR_FINAL = 1.6e-6
#: ``feature_lr``: the DC coefficient (f_dc).  [TRN-02]
FEATURE_LR = 0.0025
#: f_rest uses ``feature_lr / 20``.  [TRN-02]
FEATURE_REST_DIVISOR = 20.0
#: ``opacity_lr`` (0.05 in 3DGS@82bc469 and DropGaussian; newer upstream 0.025).  [TRN-02]
OPACITY_LR = 0.05
#: ``scaling_lr``.  [TRN-02]
SCALING_LR = 0.005
#: ``rotation_lr``.  [TRN-02]
ROTATION_LR = 0.001
#: ``getNerfppNorm``: radius = 1.1 x the largest distance of a training camera centre from
#: their mean.  [TRN-02]
EXTENT_MARGIN = 1.1
#: ``oneupSHdegree`` every 1000 iterations (train.py ``iteration % 1000 == 0``).  [TRN-03]
SH_DEGREE_INTERVAL = 1000
#: Largest SH degree (``sh_degree = 3``).  [TRN-03]
SH_MAX_DEGREE = 3


def scene_extent(centers) -> float:
    """``EXTENT_MARGIN * max_i |c_i - mean(c)|`` over training camera centres (V, 3) (TRN-02).
    One training view gives 0 (positions then get learning rate 0, as in 3DGS)."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        raise ValueError("scene_extent: no camera centres")
    return float(EXTENT_MARGIN * np.max(np.linalg.norm(c - c.mean(axis=0), axis=1)))


def position_lr(t: int, horizon: int, extent: float) -> float:
    """Log-linear decay from POSITION_LR_INIT * extent at t = 0 to POSITION_LR_FINAL * extent at
    t >= horizon (get_expon_lr_func with lr_delay_steps = 0, so the delay multiplier is
    inactive) (TRN-03).  t is the 1-based iteration."""
    a, b = POSITION_LR_INIT * extent, POSITION_LR_FINAL * extent
    if t < 0 or (a == 0.0 and b == 0.0):
        return 0.0
    u = min(max(t / horizon, 0.0), 1.0)
    return float(math.exp((1.0 - u) * math.log(a) + u * math.log(b)))


def sh_lr(k: int) -> np.ndarray:
    """(1, K, 1) per-coefficient lr of the (N, K, 3) SH array: FEATURE_LR for the DC slice,
    FEATURE_LR / FEATURE_REST_DIVISOR for the rest (TRN-02)."""
    lr = np.full((1, k, 1), FEATURE_LR / FEATURE_REST_DIVISOR)
    lr[0, 0, 0] = FEATURE_LR
    return lr


def learning_rates(t: int, horizon: int, extent: float, k: int) -> dict:
    """Learning rate of every parameter of refgs.Gaussians at iteration t (TRN-02, TRN-03)."""
    return {"means": position_lr(t, horizon, extent), "log_scales": SCALING_LR,
            "quats": ROTATION_LR, "opacity_logits": OPACITY_LR, "sh": sh_lr(k)}


def sh_degree_at(t: int, max_degree: int = SH_MAX_DEGREE, interval: int = SH_DEGREE_INTERVAL) -> int:
    """Active SH degree at iteration t: starts at 0, +1 at every multiple of ``interval``
    (raised before rendering that iteration), at most ``max_degree`` (TRN-03)."""
    return int(min(max_degree, t // interval))


__all__ = ["scene_extent", "position_lr", "sh_lr", "learning_rates", "sh_degree_at",
           "POSITION_LR_INIT", "POSITION_LR_FINAL", "FEATURE_LR", "FEATURE_REST_DIVISOR",
           "OPACITY_LR", "SCALING_LR", "ROTATION_LR", "EXTENT_MARGIN", "SH_DEGREE_INTERVAL",
           "SH_MAX_DEGREE"]
