"""The 3DGS SSIM and its gradient (MET-02, MET-04), and the training loss L1 + D-SSIM with its
gradient (MET-08), as compiled, threaded passes over rows.

The same formulas as ``refgs.metrics.ssim.ssim_and_grad`` (the readable spec, whose docstring and
docs/derivations/ssim_loss.md give the chain); what is compiled is the separable Gaussian
filtering -- eight filtered maps per call -- fused with the pointwise chain so that every
intermediate row stays in cache:

    pass 1, per output row i of channel p: the five moments x, y, x², y², xy filtered along H
            (the 11 input rows i-5..i+5, products formed on the fly), then along W; the SSIM map
            row and the three adjoint inputs of the chain; those filtered along W with the
            reversed kernel (the adjoint's first axis)  ->  smap (C, H, W), adjw (3C, H, W)
    pass 2, per row: adjw filtered along H (reversed kernel), combined into d SSIM / d x

Before them, pass 0 turns the (H, W, C) images into float64 channel planes and checks them
finite (one threaded pass, no intermediate copies).  :func:`l1_ssim_loss` (TRN-08), the
training loss, runs the three passes as one: each work item walks a band of rows of one channel
with the three stages 5 rows behind one another, its rows held in rings of 16 rows (in cache)
instead of (C, H, W) planes (in memory), and adds the L1 subgradient in pass 2's row loop, so
the loss writes nothing but its gradient and takes no numpy pass over the image at all.

Each pass is split by rows over ``numba.get_num_threads()`` threads
(``refgs.fast.render.parallel_for``); every output element is a sum over the same 11 taps in a
fixed order (a = 0..10, zero border), whatever the thread count, so the result is deterministic;
it differs from scipy's ``correlate1d`` only by the order of those sums (agreement ~1e-16
relative, tests/test_fast_ssim.py).  Along H the taps that fall outside the image are skipped,
along W the row is zero-padded (a tap on the padding adds 0): the sums of the separate
row / column kernels this replaces, operation for operation.  float64 throughout, as the reference.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..metrics.ssim import SSIM_C1, SSIM_C2, SSIM_PAD, SSIM_WINDOW, gaussian_kernel_1d
from .render import parallel_for

#: the window (refgs.metrics.ssim.gaussian_kernel_1d) and its reverse, the adjoint's (MET-04)
_G = gaussian_kernel_1d()
_G_REV = np.ascontiguousarray(_G[::-1])
#: the interior-row code below spells out the 11 taps of the 3DGS window
assert SSIM_WINDOW == 11 and SSIM_PAD == 5


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _taps11(g, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10):
    """sum_a g[a] s_a accumulated from 0.0 in the order a = 0..10 (the separate kernels' order)."""
    acc = 0.0
    acc += g[0] * s0
    acc += g[1] * s1
    acc += g[2] * s2
    acc += g[3] * s3
    acc += g[4] * s4
    acc += g[5] * s5
    acc += g[6] * s6
    acc += g[7] * s7
    acc += g[8] * s8
    acc += g[9] * s9
    acc += g[10] * s10
    return acc


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _sq(v):
    return v * v


@njit(nogil=True, cache=True, error_model="numpy")
def _along_w(buf, w, g, out):
    """out[j] = sum_a g[a] buf[j + a], a = 0..10, for j < w: a row's W-pass on its zero-padded
    copy ``buf`` (w + 10,)."""
    for j in range(w):
        out[j] = _taps11(g, buf[j], buf[j + 1], buf[j + 2], buf[j + 3], buf[j + 4], buf[j + 5],
                         buf[j + 6], buf[j + 7], buf[j + 8], buf[j + 9], buf[j + 10])


@njit(nogil=True, cache=True, error_model="numpy")
def _moments_h(xp, yp, i, h, mask, g, hb):
    """The H-pass of the five moments at image row i (of H = h) into hb[k, 5 : 5 + W] (k: x, y,
    x², y², xy): sum over the input rows i - 5 .. i + 5 inside the image, in tap order.  Image
    row ii is row ``ii & mask`` of xp, yp (R, W): a channel plane (mask -1) or a ring of rows
    (mask R - 1, :func:`_pass_loss`)."""
    w = xp.shape[1]
    r = SSIM_PAD
    if r <= i < h - r:
        # all 11 rows inside: each moment in its own loop over j that reads one or two whole
        # row stores (so LLVM needs one alias check per store and vectorises it), sums in
        # registers
        k0, k1, k2, k3 = (i - 5) & mask, (i - 4) & mask, (i - 3) & mask, (i - 2) & mask
        k4, k5, k6, k7 = (i - 1) & mask, i & mask, (i + 1) & mask, (i + 2) & mask
        k8, k9, k10 = (i + 3) & mask, (i + 4) & mask, (i + 5) & mask
        for j in range(w):
            hb[0, r + j] = _taps11(g, xp[k0, j], xp[k1, j], xp[k2, j], xp[k3, j], xp[k4, j],
                                   xp[k5, j], xp[k6, j], xp[k7, j], xp[k8, j], xp[k9, j],
                                   xp[k10, j])
        for j in range(w):
            hb[1, r + j] = _taps11(g, yp[k0, j], yp[k1, j], yp[k2, j], yp[k3, j], yp[k4, j],
                                   yp[k5, j], yp[k6, j], yp[k7, j], yp[k8, j], yp[k9, j],
                                   yp[k10, j])
        for j in range(w):
            hb[2, r + j] = _taps11(g, _sq(xp[k0, j]), _sq(xp[k1, j]), _sq(xp[k2, j]),
                                   _sq(xp[k3, j]), _sq(xp[k4, j]), _sq(xp[k5, j]),
                                   _sq(xp[k6, j]), _sq(xp[k7, j]), _sq(xp[k8, j]),
                                   _sq(xp[k9, j]), _sq(xp[k10, j]))
        for j in range(w):
            hb[3, r + j] = _taps11(g, _sq(yp[k0, j]), _sq(yp[k1, j]), _sq(yp[k2, j]),
                                   _sq(yp[k3, j]), _sq(yp[k4, j]), _sq(yp[k5, j]),
                                   _sq(yp[k6, j]), _sq(yp[k7, j]), _sq(yp[k8, j]),
                                   _sq(yp[k9, j]), _sq(yp[k10, j]))
        for j in range(w):
            hb[4, r + j] = _taps11(g, xp[k0, j] * yp[k0, j], xp[k1, j] * yp[k1, j],
                                   xp[k2, j] * yp[k2, j], xp[k3, j] * yp[k3, j],
                                   xp[k4, j] * yp[k4, j], xp[k5, j] * yp[k5, j],
                                   xp[k6, j] * yp[k6, j], xp[k7, j] * yp[k7, j],
                                   xp[k8, j] * yp[k8, j], xp[k9, j] * yp[k9, j],
                                   xp[k10, j] * yp[k10, j])
        return
    for k in range(5):                       # border rows: the taps inside, in order
        for j in range(w):
            hb[k, r + j] = 0.0
    for a in range(g.shape[0]):
        ii = i + a - r
        if 0 <= ii < h:
            ga = g[a]
            xs = xp[ii & mask]
            ys = yp[ii & mask]
            for j in range(w):
                xv = xs[j]
                yv = ys[j]
                hb[0, r + j] += ga * xv
                hb[1, r + j] += ga * yv
                hb[2, r + j] += ga * (xv * xv)
                hb[3, r + j] += ga * (yv * yv)
                hb[4, r + j] += ga * (xv * yv)


@njit(nogil=True, cache=True, error_model="numpy")
def _ssim_row(m_x, m_y, m_xx, m_yy, m_xy, w, inv_n, c1, c2, srow, g_mu, g_xx, g_xy):
    """The pointwise chain of one row from its filtered moments (the reference's expressions in
    its order): srow the SSIM map; g_mu, g_xx, g_xy the adjoint inputs (grad of mu_x, of m_xx, of
    m_xy).  Every array a separate 1D argument, so that LLVM vectorises the loop, divisions
    included."""
    for j in range(w):
        mu_x = m_x[j]
        mu_y = m_y[j]
        s_xx = m_xx[j] - mu_x * mu_x
        s_yy = m_yy[j] - mu_y * mu_y
        s_xy = m_xy[j] - mu_x * mu_y
        a1 = 2.0 * mu_x * mu_y + c1
        a2 = 2.0 * s_xy + c2
        b1 = mu_x * mu_x + mu_y * mu_y + c1
        b2 = s_xx + s_yy + c2
        sv = (a1 * a2) / (b1 * b2)
        d_a1 = a2 / (b1 * b2)
        d_a2 = a1 / (b1 * b2)
        d_b1 = -sv / b1
        d_b2 = -sv / b2
        srow[j] = sv
        g_mu[j] = inv_n * 2.0 * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2))
        g_xx[j] = inv_n * d_b2
        g_xy[j] = inv_n * 2.0 * d_a2


@njit(nogil=True, cache=True, error_model="numpy")
def _pass_moments(lo, hi, x, y, g, g_rev, inv_n, c1, c2, smap, adjw):
    """Pass 1 for channel-rows lo..hi of (C, H, W) x, y: smap (C, H, W) the SSIM map; adjw
    (3C, H, W) the chain's three adjoint inputs (grad of mu_x, of m_xx, of m_xy; the reference's
    expressions in its order) after the adjoint's W-pass."""
    c = x.shape[0]
    h = x.shape[1]
    w = x.shape[2]
    r = SSIM_PAD
    hb = np.zeros((5, w + 2 * r))            # H-pass rows, zero-padded for the W-pass
    mom = np.empty((5, w))
    ab = np.zeros((3, w + 2 * r))            # adjoint inputs, zero-padded for their W-pass
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        _moments_h(x[p], y[p], i, h, -1, g, hb)
        for k in range(5):
            _along_w(hb[k], w, g, mom[k])
        _ssim_row(mom[0], mom[1], mom[2], mom[3], mom[4], w, inv_n, c1, c2, smap[p, i],
                  ab[0, r:], ab[1, r:], ab[2, r:])
        for k in range(3):
            _along_w(ab[k], w, g_rev, adjw[k * c + p, i])


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _adjoint_h(adjw, p, i, c, h, w, g_rev, t, mask):
    """t (3, W) = the adjoint's H-pass (reversed kernel) of the three planes adjw[k C + p] at
    image row i (of H = h): the taps inside the image, in tap order; image row ii is row
    ``ii & mask`` of a plane (mask -1: whole planes; R - 1: rings of R rows)."""
    r = SSIM_PAD
    for k in range(3):
        q = k * c + p
        sp = adjw[q]
        if r <= i < h - r:
            k0, k1, k2, k3 = (i - 5) & mask, (i - 4) & mask, (i - 3) & mask, (i - 2) & mask
            k4, k5, k6, k7 = (i - 1) & mask, i & mask, (i + 1) & mask, (i + 2) & mask
            k8, k9, k10 = (i + 3) & mask, (i + 4) & mask, (i + 5) & mask
            for j in range(w):
                t[k, j] = _taps11(g_rev, sp[k0, j], sp[k1, j], sp[k2, j], sp[k3, j], sp[k4, j],
                                  sp[k5, j], sp[k6, j], sp[k7, j], sp[k8, j], sp[k9, j],
                                  sp[k10, j])
        else:
            for j in range(w):
                t[k, j] = 0.0
            for a in range(g_rev.shape[0]):
                ii = i + a - r
                if 0 <= ii < h:
                    ga = g_rev[a]
                    s = sp[ii & mask]
                    for j in range(w):
                        t[k, j] += ga * s[j]


@njit(nogil=True, cache=True, error_model="numpy")
def _pass_adjoint(lo, hi, adjw, x, y, g_rev, grad):
    """Pass 2 for channel-rows lo..hi: the adjoint's H-pass of adjw and the combination
    grad[i, j, p] = f^T(g_mu_x) + 2 x f^T(g_m_xx) + y f^T(g_m_xy) (channel-last output)."""
    c = x.shape[0]
    h = x.shape[1]
    w = x.shape[2]
    t = np.empty((3, w))
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        _adjoint_h(adjw, p, i, c, h, w, g_rev, t, -1)
        for j in range(w):
            grad[i, j, p] = t[0, j] + 2.0 * x[p, i, j] * t[1, j] + y[p, i, j] * t[2, j]


@njit(nogil=True, cache=True, error_model="numpy")
def _pass_planes(lo, hi, img, gt, x, y, bad):
    """For channel-rows lo..hi of (H, W, C) img, gt (float32 or float64): x[p, i] = img[i, :, p]
    and y[p, i] = gt[i, :, p] in float64 (exact: what ``astype(float64)`` gives); bad[item] =
    how many of the row's 2 W values are not finite."""
    h = x.shape[1]
    w = x.shape[2]
    for item in range(lo, hi):
        p = item // h
        i = item - p * h
        nb = 0
        for j in range(w):
            a = np.float64(img[i, j, p])
            b = np.float64(gt[i, j, p])
            x[p, i, j] = a
            y[p, i, j] = b
            nb += (not math.isfinite(a)) + (not math.isfinite(b))
        bad[item] = nb


#: image rows of one channel per work item of :func:`_pass_loss`: each item also filters the 10
#: rows around its band (their moments feed its rows' adjoint), so longer bands repeat less
#: (10 / 64 of the moments' work at 64) and shorter ones balance the threads better (a 378-row
#: fern view gives 3 x 6 = 18 items)
LOSS_BAND_ROWS = 64
#: rows of the ring stores of :func:`_pass_loss` (at least the 11 live rows of a tap window, a
#: power of two so that image row ii sits at ii & (_RING - 1))
_RING = 16


@njit(nogil=True, cache=True, error_model="numpy")
def _pass_loss(lo, hi, img, gt, n_bands, g, g_rev, inv_n, c1, c2, w_l1, w_ssim, n, grad,
               ssim_rows, l1_rows, bad):
    """:func:`l1_ssim_loss` for work items lo..hi, item = p n_bands + band: image rows
    band LOSS_BAND_ROWS .. + LOSS_BAND_ROWS of channel p, from (H, W, C) img and gt.

    One walk down the rows k of the band and the 10 on either side, three stages behind one
    another: row k read into float64 ring stores (exact: ``astype(float64)``; its non-finite
    values counted in bad), the moments' H- and W-passes, the pointwise chain and the adjoint's
    W-pass at row k - 5 (as :func:`_pass_moments`), then at row k - 10 the adjoint's H-pass and
    grad[i, j, p] = w_l1 sign(x - y) / n - w_ssim d SSIM / d x, rounded once to grad's dtype
    (as ``refgs.train.loss.photometric_loss``, element for element).  Every filtered value is
    the same sum in the same order as in the separate passes; the rings keep the rows in cache
    instead of whole (C, H, W) planes in memory.  ssim_rows / l1_rows [p H + i]: row i's sums of
    the SSIM map and of |x - y|, in column order."""
    h = img.shape[0]
    w = img.shape[1]
    r = SSIM_PAD
    m = _RING - 1
    X = np.empty((_RING, w))
    Y = np.empty((_RING, w))
    adj = np.empty((3, _RING, w))            # the chain's adjoint inputs after their W-pass
    hb = np.zeros((5, w + 2 * r))            # H-pass rows, zero-padded for the W-pass
    mom = np.empty((5, w))
    ab = np.zeros((3, w + 2 * r))            # adjoint inputs, zero-padded for their W-pass
    srow = np.empty(w)
    t = np.empty((3, w))
    for item in range(lo, hi):
        p = item // n_bands
        i0 = (item - p * n_bands) * LOSS_BAND_ROWS
        i1 = min(h, i0 + LOSS_BAND_ROWS)
        k_end = min(h, i1 + 2 * r)                               # the last row read + 1
        for k in range(max(0, i0 - 2 * r), k_end + 2 * r):
            if k < k_end:                                        # read row k
                nb = 0
                for j in range(w):
                    xv = np.float64(img[k, j, p])
                    yv = np.float64(gt[k, j, p])
                    X[k & m, j] = xv
                    Y[k & m, j] = yv
                    nb += (not math.isfinite(xv)) + (not math.isfinite(yv))
                if i0 <= k < i1:
                    bad[p * h + k] = nb
            km = k - r                                           # moments of row k - 5
            if max(0, i0 - r) <= km < min(h, i1 + r):
                _moments_h(X, Y, km, h, m, g, hb)
                for q in range(5):
                    _along_w(hb[q], w, g, mom[q])
                _ssim_row(mom[0], mom[1], mom[2], mom[3], mom[4], w, inv_n, c1, c2, srow,
                          ab[0, r:], ab[1, r:], ab[2, r:])
                for q in range(3):
                    _along_w(ab[q], w, g_rev, adj[q, km & m])
                if i0 <= km < i1:
                    acc = 0.0
                    for j in range(w):
                        acc += srow[j]
                    ssim_rows[p * h + km] = acc
            i = k - 2 * r                                        # gradient of row k - 10
            if i0 <= i < i1:
                _adjoint_h(adj, 0, i, 1, h, w, g_rev, t, m)
                ki = i & m
                acc = 0.0
                for j in range(w):
                    xv = X[ki, j]
                    yv = Y[ki, j]
                    g_s = t[0, j] + 2.0 * xv * t[1, j] + yv * t[2, j]
                    d = xv - yv
                    sgn = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
                    grad[i, j, p] = w_l1 * (sgn / n) - w_ssim * g_s  # rounded to grad's dtype
                    acc += abs(d)
                l1_rows[p * h + i] = acc


#: input dtypes :func:`_pass_planes` is compiled for (others are converted by numpy first)
_PLANE_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


def _checked_pair(img, gt, name: str) -> tuple[np.ndarray, np.ndarray, tuple]:
    """img and gt as (H, W, C) arrays of float32 or float64 (others converted by numpy) and
    img's shape; ValueError naming ``name`` for mismatched shapes or other ranks (the
    reference's checks and messages; finiteness is checked by the passes that read them)."""
    a, b = np.asarray(img), np.asarray(gt)
    if a.shape != b.shape:
        raise ValueError(f"{name}: img and gt must have the same shape, got {a.shape} "
                         f"and {b.shape}")
    if a.ndim not in (2, 3) or a.size == 0:
        raise ValueError(f"{name}: expected images of shape (H, W) or (H, W, C), "
                         f"got {a.shape}")
    shape = a.shape
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.dtype not in _PLANE_DTYPES or b.dtype not in _PLANE_DTYPES:
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return a, b, shape


def _finite_or_error(bad, name: str) -> None:
    if bad.any():
        raise ValueError(f"{name}: img and gt must contain only finite values")


def _image_pair(img, gt, name: str = "ssim_and_grad") -> tuple[np.ndarray, np.ndarray, tuple]:
    """float64 channel planes (C, H, W) of img and gt and img's shape (:func:`_checked_pair`;
    ValueError for non-finite values), converted by the threaded :func:`_pass_planes` (no
    intermediate copies)."""
    a, b, shape = _checked_pair(img, gt, name)
    h, w, c = a.shape
    x, y = np.empty((c, h, w)), np.empty((c, h, w))
    bad = np.empty(c * h, np.int64)
    parallel_for(_pass_planes, c * h, a, b, x, y, bad)
    _finite_or_error(bad, name)
    return x, y, shape


def _moments(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1 over the planes: the SSIM map (C, H, W) and the adjoint inputs (3C, H, W)."""
    c, h, w = x.shape
    smap = np.empty((c, h, w))
    adjw = np.empty((3 * c, h, w))
    parallel_for(_pass_moments, c * h, x, y, _G, _G_REV, 1.0 / (c * h * w), SSIM_C1, SSIM_C2,
                 smap, adjw)
    return smap, adjw


def _out_dtype(img) -> np.dtype:
    dt = np.asarray(img).dtype
    return dt if np.issubdtype(dt, np.floating) else np.dtype(np.float64)


def ssim_and_grad(img: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """SSIM(img, gt) and d SSIM / d img: ``refgs.metrics.ssim.ssim_and_grad``, compiled.

    Shapes (H, W, C) or (H, W); value a Python float, grad with img's shape and floating dtype.
    """
    x, y, shape = _image_pair(img, gt)
    c, h, w = x.shape
    smap, adjw = _moments(x, y)
    grad = np.empty((h, w, c))
    parallel_for(_pass_adjoint, c * h, adjw, x, y, _G_REV, grad)
    return float(np.mean(smap)), grad.reshape(shape).astype(_out_dtype(img), copy=False)


def l1_ssim_loss(render: np.ndarray, gt: np.ndarray, w_l1: float, w_ssim: float
                 ) -> tuple[float, np.ndarray]:
    """The training loss w_l1 L1 + w_ssim (1 - SSIM) and its gradient in one compiled chain
    (MET-08; TRN-08: what ``refgs.train.loss.photometric_loss`` computes from its form and
    lambda, with this backend's SSIM).

    render, gt: (H, W, C) or (H, W), same shape, finite.  Returns ``(loss, grad)``: grad with
    render's shape and floating dtype (float64 for integer input), element for element the
    reference's ``w_l1 sign(d) / N - w_ssim dSSIM/d render`` rounded once to that dtype
    (bit-identical); the loss a Python float whose L1 and SSIM means are summed by rows (they
    may differ from the reference's pairwise ``np.mean`` in the last bits).  One compiled pass
    over bands of rows (:func:`_pass_loss`): no (C, H, W) intermediate is written.
    """
    a, b, shape = _checked_pair(render, gt, "l1_ssim_loss")
    h, w, c = a.shape
    n = c * h * w
    n_bands = -(-h // LOSS_BAND_ROWS)
    grad = np.empty((h, w, c), _out_dtype(render))
    ssim_rows, l1_rows = np.empty(c * h), np.empty(c * h)
    bad = np.empty(c * h, np.int64)
    parallel_for(_pass_loss, c * n_bands, a, b, n_bands, _G, _G_REV, 1.0 / n, SSIM_C1, SSIM_C2,
                 float(w_l1), float(w_ssim), float(n), grad, ssim_rows, l1_rows, bad)
    _finite_or_error(bad, "l1_ssim_loss")
    s = float(ssim_rows.sum()) / n
    l1 = float(l1_rows.sum()) / n
    return float(w_l1) * l1 + float(w_ssim) * (1.0 - s), grad.reshape(shape)


__all__ = ["ssim_and_grad", "l1_ssim_loss"]
