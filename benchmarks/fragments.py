"""The pixel-Gaussian fragments a refgs.fast render blends, counted per Gaussian (benchmarks only).

    count, weight = blended_fragments(out)     # out: the RenderOutput of refgs.fast.render

A fragment is blended when its power is <= 0 and its alpha min(cap, o G) >= 1/255, before its
pixel stops (RAS-03..RAS-06): each pixel's live tile list is walked up to its last blended slot
(``cache["last"]``), in float64.  ``count`` (N,) int64: blended fragments per Gaussian;
``weight`` (N,) float64: their blending weights alpha T summed.  Used by train_profile.py (the
work of an iteration) and gaussian_use.py (Gaussians that never blend); the benchmarks import it
as a sibling module (run them as ``python benchmarks/NAME.py``).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=False)
def _walk(gauss, offsets, last, means2d, conics, opac, cap, amin, gx, tile, count, weight):
    """Adds each pixel's blended fragments to count / weight of their Gaussians."""
    H, W = last.shape
    for t in range(offsets.size - 1):
        ty, tx = t // gx, t % gx
        start = offsets[t]
        for i in range(ty * tile, min(H, ty * tile + tile)):
            for j in range(tx * tile, min(W, tx * tile + tile)):
                T = 1.0
                for s in range(last[i, j]):
                    g = gauss[start + s]
                    dx = means2d[g, 0] - (j + 0.5)
                    dy = means2d[g, 1] - (i + 0.5)
                    p = -0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) \
                        - conics[g, 1] * dx * dy
                    if p <= 0.0:
                        a = min(cap, opac[g] * np.exp(p))
                        if a >= amin:
                            count[g] += 1
                            weight[g] += a * T
                            T *= 1.0 - a


def blended_fragments(out) -> tuple[np.ndarray, np.ndarray]:
    """(count (N,) int64, weight (N,) float64) of a refgs.fast render (module docstring)."""
    from refgs.constants import ALPHA_MIN, TILE_SIZE

    c = out.cache
    n = out.means2d.shape[0]
    count, weight = np.zeros(n, np.int64), np.zeros(n)
    m2 = np.asarray(c.get("means2d_compositing", out.means2d), np.float64)
    _walk(c["lists"]["gauss"], c["lists"]["offsets"], c["last"], m2,
          out.conics.astype(np.float64), out.opacities.astype(np.float64),
          float(c["profile"].alpha_max), float(ALPHA_MIN), -(-out.alpha.shape[1] // TILE_SIZE),
          TILE_SIZE, count, weight)
    return count, weight
