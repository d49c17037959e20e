"""The photometric training loss, L1 + D-SSIM, with its hand-derived gradient (spec clause MET-08).

Two forms are in use (docs/spec/metrics.md MET-08; peers.md sections 1.5 and 3.1):

    "l1_plus":  L = L1 + lambda (1 - SSIM)              DropGaussian train.py L86, and the default
                                                        of every sparse-view method here
    "blend":    L = (1 - lambda) L1 + lambda (1 - SSIM)  original 3DGS train.py@82bc469

L1 = mean |render - gt| over all pixels and channels; SSIM is the 3DGS SSIM (MET-02) with the
render as the variable.  Gradient derivation: docs/derivations/ssim_loss.md.  Tests:
tests/test_loss.py.
"""
from __future__ import annotations

import numpy as np

from ..metrics.ssim import ssim_and_grad

#: Weight of the D-SSIM term (3DGS arguments/__init__.py ``lambda_dssim = 0.2``; DropGaussian
#: arguments/__init__.py L75-91 keeps 0.2 and hard-codes ``0.2`` in train.py L86).  [MET-08]
LAMBDA_DSSIM = 0.2
#: DropGaussian's form (DCVL-3D/DropGaussian_release@c13da4a train.py L86): L1 + lambda (1 - SSIM).
FORM_L1_PLUS = "l1_plus"
#: Original 3DGS form (graphdeco-inria/gaussian-splatting@82bc469 train.py):
#: (1 - lambda) L1 + lambda (1 - SSIM).
FORM_BLEND = "blend"
LOSS_FORMS = (FORM_L1_PLUS, FORM_BLEND)


def l1_and_grad(render: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """L1 = mean |render - gt| (float64) and its (sub)gradient sign(render - gt) / N (MET-08).

    At render == gt the subgradient 0 is used (``np.sign(0) = 0``; torch's ``abs`` backward
    also gives 0 there).  Shapes must match; the gradient has render's shape, float64.
    """
    d = np.asarray(render, dtype=np.float64) - np.asarray(gt, dtype=np.float64)
    return float(np.mean(np.abs(d))), np.sign(d) / d.size


def photometric_loss(render: np.ndarray, gt: np.ndarray, lambda_dssim: float = LAMBDA_DSSIM,
                     form: str = FORM_L1_PLUS, ssim_fn=None, loss_fn=None
                     ) -> tuple[float, np.ndarray]:
    """Training loss and d loss / d render (MET-08).

    render, gt: (H, W, C) or (H, W), same shape, finite (the render is already clamped to [0, 1]
    as DropGaussian's ``render()`` does, peers.md 3.1; the clamp's gradient belongs to the caller).
    lambda_dssim in [0, 1].  form: "l1_plus" (default) or "blend" (see module docstring).
    Returns ``(loss, grad)``: loss a Python float computed in float64; grad with render's shape
    and render's floating dtype (float64 for integer input).  ``ssim_fn``: an implementation of
    ``refgs.metrics.ssim.ssim_and_grad`` (the default) with its signature, e.g. a backend's
    compiled one (``refgs.fast.ssim.ssim_and_grad``, TRN-08).  ``loss_fn``: a backend's whole
    chain instead, ``loss_fn(render, gt, w_l1, w_ssim) -> (w_l1 L1 + w_ssim (1 - SSIM), grad)``
    with the gradient computed as below (``refgs.fast.ssim.l1_ssim_loss``); it is called with
    the form's weights and the shape check of this function.
    """
    if form not in LOSS_FORMS:
        raise ValueError(f"photometric_loss: form must be one of {LOSS_FORMS}, got {form!r}")
    lam = float(lambda_dssim)
    if not (0.0 <= lam <= 1.0):
        raise ValueError(f"photometric_loss: lambda_dssim must lie in [0, 1], got {lambda_dssim!r}")
    if np.shape(render) != np.shape(gt):
        raise ValueError(f"photometric_loss: render and gt must have the same shape, got "
                         f"{np.shape(render)} and {np.shape(gt)}")
    w_l1 = 1.0 if form == FORM_L1_PLUS else 1.0 - lam
    if loss_fn is not None:
        return loss_fn(render, gt, w_l1, lam)
    # ssim_and_grad validates the rest (2 or 3 dimensions, finite values).
    s, g_s = (ssim_fn or ssim_and_grad)(np.asarray(render, dtype=np.float64), gt)
    l1, g_l1 = l1_and_grad(render, gt)
    loss = w_l1 * l1 + lam * (1.0 - s)
    grad = w_l1 * g_l1 - lam * g_s
    dtype = np.asarray(render).dtype
    out_dtype = dtype if np.issubdtype(dtype, np.floating) else np.float64
    return float(loss), grad.astype(out_dtype, copy=False)
