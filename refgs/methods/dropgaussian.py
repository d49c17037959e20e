"""DropGaussian (official release DCVL-3D/DropGaussian_release@c13da4a, peers.md 3.1) [DG-01].

During training each Gaussian is kept with probability 1 - r, r(t) = R_MAX t / T, and kept
Gaussians' activated opacity is multiplied by 1 / (1 - r) before the alpha cap applies (the
compensation of torch.nn.Dropout applied to a vector of ones, gaussian_renderer/__init__.py
L86-97).  Nothing changes at test time.
"""
from __future__ import annotations

import numpy as np

#: drop_rate = 0.2 * (iteration / 10000): the largest drop rate, reached at t = T  [DG-01]
R_MAX = 0.2


def drop_rate(t: int, total: int, r_max: float = R_MAX) -> float:
    """r(t) = r_max t / T [DG-01]."""
    if total <= 0:
        raise ValueError(f"--iters: expected a positive number of iterations, got {total}")
    return r_max * float(t) / float(total)


def drop_opacity_scale(n: int, t: int, total: int, rng: np.random.Generator,
                       r_max: float = R_MAX) -> tuple[np.ndarray, np.ndarray]:
    """Per-Gaussian opacity factors for one training render [DG-01, DG-02].

    Returns ``(scale (N,) float64, keep (N,) bool)``: scale = keep / (1 - r), i.e. 0 for dropped
    Gaussians and 1/(1 - r) for kept ones (it may push o/(1-r) above 1; the renderer's alpha cap
    then applies, as in the official code).
    """
    r = drop_rate(t, total, r_max)
    keep = rng.random(n) >= r
    scale = np.where(keep, 1.0 / (1.0 - r), 0.0)
    return scale, keep
