"""The 3DGS SSIM and its gradient (MET-02, MET-04) as compiled, threaded separable filters.

The same formulas as ``refgs.metrics.ssim.ssim_and_grad`` (the readable spec, whose docstring and
docs/derivations/ssim_loss.md give the chain); only the separable Gaussian filtering -- eight
filtered maps per call, 95 % of its time -- is compiled: the five moments x, y, x², y², xy are
filtered in one fused pass over a stack of 5C image planes, the three adjoint maps in one pass
over 3C planes (contiguous rows, so the inner loops run along memory), each pass split by rows over ``numba.get_num_threads()`` threads
(``refgs.fast.render.parallel_for``).  Every output element is a sum over the same 11 taps in a
fixed order, whatever the thread count, so the result is deterministic; it differs from scipy's
``correlate1d`` only by the order of those sums (agreement ~1e-16 relative, tests/test_fast_ssim.py).
float64 throughout, as the reference.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..metrics.ssim import SSIM_C1, SSIM_C2, _G, _as_image_pair
from .render import parallel_for

_R = len(_G) // 2


@njit(nogil=True, cache=True)
def _correlate_rows(lo, hi, src, dst, g):
    """Along H: dst[p, i] = sum_a g[a] src[p, i + a - r] for planes*rows lo..hi of (P, H, W)."""
    h = src.shape[1]
    w = src.shape[2]
    r = g.shape[0] // 2
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        out = dst[p, i]
        for j in range(w):
            out[j] = 0.0
        for a in range(g.shape[0]):
            ii = i + a - r
            if 0 <= ii < h:
                ga = g[a]
                s = src[p, ii]
                for j in range(w):
                    out[j] += ga * s[j]


@njit(nogil=True, cache=True)
def _correlate_cols(lo, hi, src, dst, g):
    """Along W: dst[p, i, j] = sum_a g[a] src[p, i, j + a - r] for planes*rows lo..hi.

    Each row is copied into a zero-padded buffer, so every tap is one unit-stride loop without
    bounds (which the compiler vectorises); the taps are summed in the order a = 0..10."""
    h = src.shape[1]
    w = src.shape[2]
    r = g.shape[0] // 2
    buf = np.zeros(w + 2 * r)
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        out = dst[p, i]
        buf[r:r + w] = src[p, i]
        out[:] = 0.0
        for a in range(g.shape[0]):
            ga = g[a]
            for j in range(w):
                out[j] += ga * buf[j + a]


def _filter(planes: np.ndarray, g: np.ndarray, first_axis: int) -> np.ndarray:
    """Separable zero-border correlation of (P, H, W) planes with g along H and W,
    H first (``first_axis`` 0, the forward filter) or W first (1, the adjoint)."""
    planes = np.ascontiguousarray(planes)     # C order: the kernels are compiled for it
    p, h, _ = planes.shape
    tmp = np.empty(planes.shape)
    out = np.empty(planes.shape)
    first, second = ((_correlate_rows, _correlate_cols) if first_axis == 0
                     else (_correlate_cols, _correlate_rows))
    parallel_for(first, p * h, planes, tmp, g)
    parallel_for(second, p * h, tmp, out, g)
    return out


@njit(nogil=True, cache=True)
def _pointwise(lo, hi, mom, c, inv_n, c1, c2, smap, adj_in):
    """Per pixel of planes*rows lo..hi: the SSIM map S and the three maps the adjoint filter takes
    (``refgs.metrics.ssim.ssim_and_grad``'s chain, same expressions in the same order)."""
    h = mom.shape[1]
    w = mom.shape[2]
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        for j in range(w):
            mu_x = mom[p, i, j]
            mu_y = mom[c + p, i, j]
            s_xx = mom[2 * c + p, i, j] - mu_x * mu_x
            s_yy = mom[3 * c + p, i, j] - mu_y * mu_y
            s_xy = mom[4 * c + p, i, j] - mu_x * mu_y
            a1 = 2.0 * mu_x * mu_y + c1
            a2 = 2.0 * s_xy + c2
            b1 = mu_x * mu_x + mu_y * mu_y + c1
            b2 = s_xx + s_yy + c2
            sv = (a1 * a2) / (b1 * b2)
            d_a1 = a2 / (b1 * b2)
            d_a2 = a1 / (b1 * b2)
            d_b1 = -sv / b1
            d_b2 = -sv / b2
            smap[p, i, j] = sv
            adj_in[p, i, j] = inv_n * 2.0 * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2))
            adj_in[c + p, i, j] = inv_n * d_b2
            adj_in[2 * c + p, i, j] = inv_n * 2.0 * d_a2


@njit(nogil=True, cache=True)
def _combine(lo, hi, adj, x, y, c, grad):
    """grad[i, j, p] = f^T(g_mu_x) + 2 x f^T(g_m_xx) + y f^T(g_m_xy) (channel-last output)."""
    h = adj.shape[1]
    w = adj.shape[2]
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        for j in range(w):
            grad[i, j, p] = (adj[p, i, j] + 2.0 * x[p, i, j] * adj[c + p, i, j]
                             + y[p, i, j] * adj[2 * c + p, i, j])


def ssim_and_grad(img: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """SSIM(img, gt) and d SSIM / d img: ``refgs.metrics.ssim.ssim_and_grad``, compiled.

    Shapes (H, W, C) or (H, W); value a Python float, grad with img's shape and floating dtype.
    """
    x, y, shape = _as_image_pair(img, gt, "ssim_and_grad")
    x = np.ascontiguousarray(np.moveaxis(x, 2, 0))               # channel planes (C, H, W)
    y = np.ascontiguousarray(np.moveaxis(y, 2, 0))
    c, h, w = x.shape
    mom = _filter(np.concatenate([x, y, x * x, y * y, x * y], axis=0), _G, 0)
    smap = np.empty((c, h, w))
    adj_in = np.empty((3 * c, h, w))
    parallel_for(_pointwise, c * h, mom, c, 1.0 / (c * h * w), SSIM_C1, SSIM_C2, smap, adj_in)
    # adjoint filter: reversed kernel, the two axes in the reverse order (gaussian_filter_adjoint)
    adj = _filter(adj_in, np.ascontiguousarray(_G[::-1]), 1)
    grad = np.empty((h, w, c))
    parallel_for(_combine, c * h, adj, x, y, c, grad)
    dt = np.asarray(img).dtype
    out_dtype = dt if np.issubdtype(dt, np.floating) else np.float64
    return float(np.mean(smap)), grad.reshape(shape).astype(out_dtype, copy=False)


__all__ = ["ssim_and_grad"]
