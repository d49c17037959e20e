"""Adam's update of one parameter array in one compiled pass (TRN-02; the backend's adam_update, TRN-08).

``refgs.train.adam.Adam.step`` is the readable spec: it builds m', v', the step and the new
parameter as whole-array numpy expressions (six temporaries of the parameter's size, ~8 % of a
fern iteration at 50k Gaussians).  :func:`adam_update` does the same arithmetic element by
element, in place, with the same operations in the same order and the same precisions -- for
float32 parameters numpy (NEP 50) computes m' and v' in float32 and the step in float64, and so
does this kernel -- so its result is bit-identical to ``Adam.step`` (tests/test_fast_adam.py).
No fast-math: LLVM may not fuse a multiply and an add into an FMA, which would change roundings.

It handles the shapes training uses (a learning rate that is a scalar or constant along rows,
frozen rows given per row or per row and column) and returns False for anything else, in which
case ``Adam.step`` falls back to its numpy expressions.  Rows are split over
``numba.get_num_threads()`` threads (``refgs.fast.render.parallel_for``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .render import parallel_for


#: rows per chunk at least (an element costs a few ns; smaller chunks are not worth a thread)
MIN_ROW_CHUNK = 4096


@njit(cache=True, nogil=True, error_model="numpy")
def _update(lo, hi, p, g, m, v, lr, keep, c1, b2, c2, bc1, sbc2, eps):
    """Rows lo..hi of p, g, m, v (N, C) contiguous, one dtype; lr (C,) float64; keep (N, K)
    bool with K dividing C -- keep[i, j // (C / K)] holds element (i, j) -- or (0, 0) for none.
    Each element is independent, so any split of the rows over threads gives the same bits.

    c1 = 1 - b1, b2, c2 = 1 - b2 in the parameter's dtype; bc1 = 1 - b1^s, sbc2 =
    sqrt(1 - b2^s), eps float64 -- the scalars of Adam.step, with the types numpy gives them.
    """
    cols = p.shape[1]
    has_keep = keep.shape[0] > 0
    rep = cols // keep.shape[1] if has_keep else 1
    # storing the float64 step in tmp rounds it to the parameter's dtype first, as numpy's
    # ``.astype(p.dtype)``
    tmp = np.empty(1, p.dtype)
    for i in range(lo, hi):
        for j in range(cols):
            if has_keep and keep[i, j // rep]:
                continue
            mi = m[i, j]
            gi = g[i, j]
            mn = mi + c1 * (gi - mi)
            vn = b2 * v[i, j] + c2 * gi * gi
            denom = np.float64(np.sqrt(vn)) / sbc2 + eps
            step = (lr[j] / bc1) * (np.float64(mn) / denom)
            tmp[0] = step
            p[i, j] = p[i, j] - tmp[0]
            m[i, j] = mn
            v[i, j] = vn


def _keep_blocks(keep: np.ndarray, shape: tuple) -> np.ndarray:
    """``keep`` broadcast against a parameter of ``shape`` as (N, K), each entry covering C / K
    consecutive elements of a row: the leading axes it has in full, the trailing ones it
    broadcasts (a frozen row (N,), frozen SH coefficients (N, K, 1)) -- without materialising the
    parameter-sized mask; other patterns are broadcast in full (K = C)."""
    n = shape[0]
    if keep.ndim == 1:
        keep = keep.reshape((-1,) + (1,) * (len(shape) - 1))
    full = np.broadcast_to(keep, shape)                # raises ValueError if it does not fit
    d = keep.ndim
    while d > 1 and keep.shape[d - 1] == 1:
        d -= 1                                         # trailing axes of length 1 broadcast
    if keep.shape[:d] == tuple(shape[:d]):
        return np.ascontiguousarray(keep.reshape(n, -1))
    return np.ascontiguousarray(full).reshape(n, -1)


def adam_update(p, g, m, v, lr, keep, step: int, betas, eps: float) -> bool:
    """Adam.step's update of one parameter in place; False (nothing changed) if the shapes are
    not ones the kernel takes.  ``keep``: None, or a bool array broadcasting against ``p``
    whose True entries keep parameter and moments unchanged."""
    if p.dtype not in (np.float32, np.float64) or p.ndim == 0 or p.shape[0] == 0:
        return False
    if not all(a.flags.c_contiguous and a.dtype == p.dtype and a.shape == p.shape
               for a in (g, m, v)) or not p.flags.c_contiguous:
        return False
    lr = np.asarray(lr, np.float64)
    if lr.ndim > p.ndim or (lr.ndim == p.ndim and lr.shape[0] != 1):
        return False                                   # a learning rate that varies by row
    n = p.shape[0]
    cols = p.size // n
    try:
        lr_cols = np.ascontiguousarray(np.broadcast_to(lr, (1,) + p.shape[1:])).reshape(cols)
        if keep is None:
            keep2 = np.zeros((0, 0), np.bool_)
        else:
            keep2 = _keep_blocks(np.asarray(keep, bool), p.shape)
    except ValueError:
        return False
    b1, b2 = float(betas[0]), float(betas[1])
    dt = p.dtype.type
    parallel_for(_update, n, p.reshape(n, cols), g.reshape(n, cols), m.reshape(n, cols),
                 v.reshape(n, cols), lr_cols, keep2, dt(1.0 - b1), dt(b2), dt(1.0 - b2),
                 1.0 - b1 ** step, float(np.sqrt(1.0 - b2 ** step)), float(eps),
                 min_chunk=MIN_ROW_CHUNK)
    return True


__all__ = ["adam_update"]
