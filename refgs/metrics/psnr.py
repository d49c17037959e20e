"""PSNR of a render against its ground truth (spec clause MET-01, docs/spec/metrics.md).

The 3DGS definition (graphdeco-inria/gaussian-splatting ``utils/image_utils.py``):
``PSNR = 20 log10(1 / sqrt(mse))`` with the mean squared error taken over every pixel and every
channel of one image, for images whose peak value is 1.  Tested in tests/test_loss.py::test_psnr_*.
"""
from __future__ import annotations

import numpy as np

#: Peak signal value; images live in [0, 1] (3DGS clamps renders to [0, 1] before evaluation,
#: peers.md section 1.5).  [MET-01]
PSNR_PEAK = 1.0


def _check_pair(img, gt, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Both images as float64 arrays of equal shape with only finite values, else ValueError."""
    a = np.asarray(img, dtype=np.float64)
    b = np.asarray(gt, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"{name}: img and gt must have the same shape, got {a.shape} and {b.shape}")
    if a.size == 0:
        raise ValueError(f"{name}: images are empty (shape {a.shape})")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError(f"{name}: img and gt must contain only finite values")
    return a, b


def psnr(img: np.ndarray, gt: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB (MET-01).

    img, gt: arrays of the same shape, e.g. (H, W, 3), values in [0, 1].  The caller clamps the
    render to [0, 1] first (as 3DGS and DropGaussian do); this function does not clamp.
    Returns ``20 log10(PSNR_PEAK / sqrt(mse))`` as a Python float, computed in float64, with
    ``mse = mean((img - gt)**2)`` over all pixels and channels.  Identical images (mse = 0) give
    ``math.inf`` (not an error and not a warning).
    """
    a, b = _check_pair(img, gt, "psnr")
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(20.0 * np.log10(PSNR_PEAK / np.sqrt(mse)))
