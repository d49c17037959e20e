"""SSIM as 3DGS computes it, its hand-derived gradient, and the scikit-image variant.

Spec: docs/spec/metrics.md, clauses MET-02 (the 3DGS formula), MET-03 (relation to scikit-image),
MET-04 (gradient).  Derivation of the gradient: docs/derivations/ssim_loss.md.
Tests: tests/test_ssim.py.

Notation (all arrays (H, W, C), float64).  ``f`` is the separable Gaussian filter: a correlation
with the normalised 1D kernel ``g`` along rows, then along columns, with a constant 0 border
("same" size output, zero padding of 5 pixels, as ``F.conv2d(..., padding=5)`` in 3DGS
``utils/loss_utils.py``).  For a render x and a ground truth y::

    mu_x = f(x)   mu_y = f(y)
    s_xx = f(x*x) - mu_x**2   s_yy = f(y*y) - mu_y**2   s_xy = f(x*y) - mu_x*mu_y
    A1 = 2 mu_x mu_y + C1     A2 = 2 s_xy + C2
    B1 = mu_x**2 + mu_y**2 + C1   B2 = s_xx + s_yy + C2
    S  = A1 A2 / (B1 B2)      (the SSIM map)        SSIM = mean(S) over pixels and channels
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

# Constants of the 3DGS SSIM (graphdeco-inria/gaussian-splatting utils/loss_utils.py@ad8f3a1;
# peers.md section 1.5).  [MET-02]
#: Side of the square Gaussian window (``window_size=11``).
SSIM_WINDOW = 11
#: Standard deviation of the Gaussian window in pixels (``gaussian(window_size, 1.5)``).
SSIM_SIGMA = 1.5
#: Zero padding on every side (``padding=window_size // 2``).
SSIM_PAD = SSIM_WINDOW // 2
#: Stabilising constants for a data range of 1 (``C1 = 0.01 ** 2``, ``C2 = 0.03 ** 2``).
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def gaussian_kernel_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Normalised 1D Gaussian (size,), float64, centred on index size // 2 (MET-02).

    ``g[k] = exp(-(k - size//2)**2 / (2 sigma**2)) / sum``.  3DGS builds it in float32; we keep
    float64 (the float32 window accounts for the ~1e-6 difference to the torch original, deps.md
    note 2).  Exactly symmetric: g[k] == g[size-1-k] bit for bit.
    """
    k = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(k * k) / (2.0 * sigma * sigma))
    return g / g.sum()


#: The kernel used everywhere in this module.
_G = gaussian_kernel_1d()


def gaussian_filter(x: np.ndarray) -> np.ndarray:
    """``f``: separable Gaussian correlation of (H, W, C) with zero border, same shape out (MET-02).

    out[i, j, c] = sum_{a,b} g[a] g[b] x[i + a - 5, j + b - 5, c], with x = 0 outside the image.
    """
    y = ndimage.correlate1d(x, _G, axis=0, mode="constant", cval=0.0)
    return ndimage.correlate1d(y, _G, axis=1, mode="constant", cval=0.0)


def gaussian_filter_adjoint(v: np.ndarray) -> np.ndarray:
    """``f^T``: the adjoint of ``gaussian_filter`` (MET-04), same shape as v.

    For a 1D zero-padded correlation out[i] = sum_k g[k] x[i + k - 5], the adjoint is
    x_bar[j] = sum_k g[k] v[j - k + 5] = sum_m g[10 - m] v[j + m - 5]: a zero-padded correlation
    with the reversed kernel.  The Gaussian is symmetric, so this equals ``gaussian_filter``; the
    reversal is written out so the code states the rule and not the coincidence
    (docs/derivations/ssim_loss.md, step 4).  Order of the two axes does not matter (they commute).
    """
    g_rev = _G[::-1]
    y = ndimage.correlate1d(v, g_rev, axis=1, mode="constant", cval=0.0)
    return ndimage.correlate1d(y, g_rev, axis=0, mode="constant", cval=0.0)


def _as_image_pair(img, gt, name: str) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Validate and return float64 (H, W, C) copies plus the caller's original shape."""
    a = np.asarray(img)
    b = np.asarray(gt)
    if a.shape != b.shape:
        raise ValueError(f"{name}: img and gt must have the same shape, got {a.shape} and {b.shape}")
    if a.ndim not in (2, 3) or a.size == 0:
        raise ValueError(f"{name}: expected images of shape (H, W) or (H, W, C), got {a.shape}")
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError(f"{name}: img and gt must contain only finite values")
    shape = a.shape
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    return a, b, shape


def _statistics(x: np.ndarray, y: np.ndarray) -> dict:
    """Filtered moments and the four SSIM factors (module docstring notation)."""
    mu_x, mu_y = gaussian_filter(x), gaussian_filter(y)
    s_xx = gaussian_filter(x * x) - mu_x * mu_x
    s_yy = gaussian_filter(y * y) - mu_y * mu_y
    s_xy = gaussian_filter(x * y) - mu_x * mu_y
    A1 = 2.0 * mu_x * mu_y + SSIM_C1
    A2 = 2.0 * s_xy + SSIM_C2
    B1 = mu_x * mu_x + mu_y * mu_y + SSIM_C1
    B2 = s_xx + s_yy + SSIM_C2
    S = (A1 * A2) / (B1 * B2)
    return {"mu_x": mu_x, "mu_y": mu_y, "A1": A1, "A2": A2, "B1": B1, "B2": B2, "S": S}


def ssim_map(img: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """The 3DGS SSIM map (MET-02): same shape as the inputs ((H, W) or (H, W, C)), float64.

    Border pixels are included, with window statistics that see the zero padding.
    """
    x, y, shape = _as_image_pair(img, gt, "ssim_map")
    return _statistics(x, y)["S"].reshape(shape)


def ssim(img: np.ndarray, gt: np.ndarray) -> float:
    """3DGS SSIM (MET-02): mean of ``ssim_map`` over all pixels and channels, a Python float.

    img, gt: (H, W, C) or (H, W), values in [0, 1] (data range 1 is built into C1, C2).
    """
    x, y, _ = _as_image_pair(img, gt, "ssim")
    return float(np.mean(_statistics(x, y)["S"]))


def ssim_and_grad(img: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """SSIM(img, gt) and d SSIM / d img, hand-derived (MET-04; docs/derivations/ssim_loss.md).

    img is the render (the variable), gt a constant.  Shapes (H, W, C) or (H, W).
    Returns ``(value, grad)``: value a Python float (computed in float64), grad with img's shape
    and img's floating dtype (float64 for integer inputs).  Chain, with N = number of entries
    and the four factors of the module docstring::

        dS/dA1 = A2/(B1 B2)   dS/dA2 = A1/(B1 B2)   dS/dB1 = -S/B1   dS/dB2 = -S/B2
        grad_mu_x = (1/N) * 2 (mu_y (dS/dA1 - dS/dA2) + mu_x (dS/dB1 - dS/dB2))
        grad_m_xy = (1/N) * 2 dS/dA2          (m_xy = f(x*y))
        grad_m_xx = (1/N) * dS/dB2            (m_xx = f(x*x))
        dSSIM/dx  = f^T(grad_mu_x) + 2 x f^T(grad_m_xx) + y f^T(grad_m_xy)
    """
    x, y, shape = _as_image_pair(img, gt, "ssim_and_grad")
    st = _statistics(x, y)
    S, A1, A2, B1, B2 = st["S"], st["A1"], st["A2"], st["B1"], st["B2"]
    inv_n = 1.0 / S.size
    d_A1 = A2 / (B1 * B2)
    d_A2 = A1 / (B1 * B2)
    d_B1 = -S / B1
    d_B2 = -S / B2
    g_mu_x = inv_n * 2.0 * (st["mu_y"] * (d_A1 - d_A2) + st["mu_x"] * (d_B1 - d_B2))
    g_m_xy = inv_n * 2.0 * d_A2
    g_m_xx = inv_n * d_B2
    grad = (gaussian_filter_adjoint(g_mu_x)
            + 2.0 * x * gaussian_filter_adjoint(g_m_xx)
            + y * gaussian_filter_adjoint(g_m_xy))
    out_dtype = np.asarray(img).dtype if np.issubdtype(np.asarray(img).dtype, np.floating) else np.float64
    return float(np.mean(S)), grad.reshape(shape).astype(out_dtype, copy=False)


def ssim_skimage(img: np.ndarray, gt: np.ndarray) -> float:
    """SSIM as scikit-image computes it with the 3DGS window (MET-03), a Python float.

    ``skimage.metrics.structural_similarity(img, gt, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1.0, channel_axis=-1)``.  It equals the mean of
    ``ssim_map`` over the interior (SSIM_PAD pixels cropped from every side) -- scikit-image drops
    the border instead of padding with zeros.  img, gt: (H, W, C) with H, W >= SSIM_WINDOW, or
    (H, W) (single channel).
    """
    from skimage.metrics import structural_similarity

    x, y, shape = _as_image_pair(img, gt, "ssim_skimage")
    if min(shape[0], shape[1]) < SSIM_WINDOW:
        raise ValueError(f"ssim_skimage: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW}, "
                         f"got shape {shape}")
    return float(structural_similarity(x, y, gaussian_weights=True, sigma=SSIM_SIGMA,
                                       use_sample_covariance=False, data_range=1.0,
                                       channel_axis=-1))
