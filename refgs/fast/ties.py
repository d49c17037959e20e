"""Near-ties of a float64 render: where a float32 render may legitimately decide differently.

The model has steps (alpha < 1/255 skips, the T stop rule, the depth order, integer radii and tile
rectangles, culls) and kinks (the gsplat alpha-cap gradient, the SH clamp at 0, the frustum
clamp).  A float32 computation perturbs their continuous inputs by ~1e-7..1e-6 relative, so where
the float64 render lies within a band of a threshold the float32 decision may flip, changing a
pixel by far more than rounding.  This module finds those places in a float64 render of
:func:`refgs.fast.render` -- fast enough for the 50k-Gaussian benchmark scene, unlike the dense
oracle/ties.py (every pixel x every Gaussian) -- so comparisons can exclude and *count* them
instead of loosening tolerances.

Per pixel (forward): ``alpha`` (a reached fragment has |ln(o G 255)| <= band), ``stop``
(|ln(T (1 - alpha) / 1e-4)| <= band for a blended or stopping fragment), ``depth`` (two
consecutive valid fragments, including the one after the stop, closer in depth than band
relative), ``geom`` (the pixel is reached by a Gaussian with a geometric near-tie).  Per pixel
(backward only): ``cap`` (gsplat: |ln(o G / cap)| <= band, where the gradient switches off).
Per Gaussian: ``geom`` (visibility, radius or tile rectangle within band of flipping) and
``kink`` (SH clamp or frustum clamp within band; its gradient rows are excluded from gradient
comparisons, the forward is continuous there).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..constants import ALPHA_MIN, TILE_SIZE
from ..projection import frustum_limits
from ..rasterize import tile_grid
from ..sh import eval_sh_colors
from . import kernels as rk
from . import tiles as tl


@dataclass(frozen=True)
class TieBands:
    """How close to a threshold counts as a near-tie (our choice, for float32 vs float64: float32
    relative rounding is 6e-8 per operation and the pipeline compounds a few dozen)."""

    alpha: float = 1e-4      # log units, |ln(o G 255)|
    stop: float = 1e-4       # log units, |ln(T (1 - alpha) / 1e-4)|
    cap: float = 1e-4        # log units, |ln(o G / cap)| (gsplat gradient only)
    depth: float = 2e-6      # relative depth gap of consecutive valid fragments
    geom: float = 2e-6       # relative distance of a radius / rectangle / cull argument to its step
    kink: float = 1e-5       # SH rgb within this of 0; |u - limit| within this times the limit


FLOAT32_BANDS = TieBands()
#: for float32 compositing of float64 per-Gaussian results (refgs.fast's float32 default,
#: ``geometry="float64"``): radii, rectangles, culls, clamps and the depth order are decided in
#: float64, so only float64-level ties remain there; the per-pixel bands are FLOAT32_BANDS'.
GEOMETRY64_BANDS = TieBands(depth=1e-12, geom=1e-12, kink=1e-12)


@njit(cache=True, nogil=True, error_model="numpy")
def _pixel_distances(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, rc, eps,
                     stop_inclusive, gx, gtie, d_alpha, d_stop, d_cap, d_depth, hit_geom):
    """Per pixel of tiles [lo, hi): smallest |ln(oG 255)|, |ln(test_T / T_MIN)|, |ln(oG / cap)|,
    relative gap of consecutive valid depths, and whether a ``gtie`` Gaussian is valid there."""
    H, W = d_alpha.shape
    one, t_min, cap, amin = rc[rk.R_ONE], rc[rk.R_T_MIN], rc[rk.R_CAP], rc[rk.R_ALPHA_MIN]
    Lm = tl.max_len(offsets, lo, hi)
    tab = np.empty((Lm, tl.N_TAB), means2d.dtype)
    cnt = np.empty(TILE_SIZE, np.int64)
    rs = np.empty((TILE_SIZE, Lm), np.int32)
    col_lo = np.empty((TILE_SIZE, Lm), np.int8)
    col_hi = np.empty((TILE_SIZE, Lm), np.int8)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        tl.gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = tl.centres(tx * TILE_SIZE, tab)
        ys = tl.centres(ty * TILE_SIZE, tab)
        tl.chords(tab, L, xs, ys, eps, True, cnt, rs, col_lo, col_hi)
        for r in range(TILE_SIZE):
            i = ty * TILE_SIZE + r
            if i >= H:
                break
            for c in range(TILE_SIZE):
                j = tx * TILE_SIZE + c
                if j >= W:
                    break
                T = one
                da = np.inf
                ds = np.inf
                dc = np.inf
                dd = np.inf
                hg = False
                z_prev = np.nan
                stopped = False
                for k in range(cnt[r]):
                    if c < col_lo[r, k] or c > col_hi[r, k]:
                        continue
                    s = rs[r, k]
                    dx = (tab[s, 0] - xs[c]) + tab[s, 10]
                    dy = (tab[s, 1] - ys[r]) + tab[s, 11]
                    power = tl.gaussian_power(tab[s, 2], tab[s, 3], tab[s, 4] * dy * dy, dx, dy,
                                              rc[rk.R_NEG_HALF])
                    if power > 0.0:
                        continue
                    oG = tab[s, 5] * math.exp(power)
                    if oG > 0.0 and not stopped:
                        da = min(da, abs(math.log(oG / amin)))
                        dc = min(dc, abs(math.log(oG / cap)))
                    alpha = min(cap, oG)
                    if alpha < amin:
                        continue
                    z = tab[s, 9]
                    if z_prev == z_prev:
                        dd = min(dd, abs(z - z_prev) / max(abs(z), 1e-300))
                    z_prev = z
                    if stopped:
                        break                       # the first valid fragment after the stop
                    if gtie[gauss[start + s]]:
                        hg = True
                    test_T = T * (one - alpha)
                    if test_T > 0.0:
                        ds = min(ds, abs(math.log(test_T / t_min)))
                    else:
                        ds = 0.0
                    if (test_T <= t_min) if stop_inclusive else (test_T < t_min):
                        stopped = True
                        continue
                    T = test_T
                d_alpha[i, j] = da
                d_stop[i, j] = ds
                d_cap[i, j] = dc
                d_depth[i, j] = dd
                hit_geom[i, j] = hg


def _frac_dist(x):
    """Distance of x to the nearest integer (inf where not finite)."""
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(x), np.abs(x - np.round(x)), np.inf)


def gaussian_ties(out, bands: TieBands = FLOAT32_BANDS) -> dict:
    """Per-Gaussian near-ties of a float64 render: ``geom`` (N,) bool (visibility, radius or tile
    rectangle within ``bands.geom`` of flipping), ``near`` (N,) bool (near/far cull tie), ``kink``
    (N,) bool (SH clamp or frustum clamp within ``bands.kink``)."""
    prof = out.cache["profile"]
    cam = out.camera
    W, H = int(cam.width), int(cam.height)
    g = out.gaussians
    Rw = np.asarray(cam.world_to_camera, np.float64)
    t = np.asarray(g.means, np.float64) @ Rw[:3, :3].T + Rw[:3, 3]
    z = t[:, 2]
    band = bands.geom
    near = np.abs(z - prof.near) <= band * np.maximum(np.abs(z), prof.near)
    if np.isfinite(prof.far):
        near |= np.abs(z - prof.far) <= band * prof.far
    live = z > 0.5 * prof.near
    a, b, c = (out.cov2d[:, k].astype(np.float64) for k in range(3))
    m = out.means2d.astype(np.float64)
    o = out.opacities.astype(np.float64)
    geom = np.zeros(z.shape, bool)
    with np.errstate(all="ignore"):
        if prof.radius_rule == "eig":
            mid = 0.5 * (a + c)
            lam1 = mid + np.sqrt(np.maximum(prof.eig_floor, mid * mid - (a * c - b * b)))
            r = prof.radius_sigma * np.sqrt(np.maximum(lam1, 0))
            geom |= _frac_dist(r) <= band * (1 + r)
            rx = ry = np.ceil(r)
            px, py = m[:, 0] - 0.5, m[:, 1] - 0.5
            args = [(px - rx, np.abs(px) + rx), (px + rx + TILE_SIZE - 1, np.abs(px) + rx + TILE_SIZE),
                    (py - ry, np.abs(py) + ry), (py + ry + TILE_SIZE - 1, np.abs(py) + ry + TILE_SIZE)]
        else:
            ext = np.minimum(prof.radius_sigma,
                             np.sqrt(2.0 * np.log(np.maximum(o, ALPHA_MIN) / ALPHA_MIN)))
            geom |= np.abs(np.log(o / ALPHA_MIN)) <= band
            rxc, ryc = ext * np.sqrt(np.maximum(a, 0)), ext * np.sqrt(np.maximum(c, 0))
            geom |= (_frac_dist(rxc) <= band * (1 + rxc)) | (_frac_dist(ryc) <= band * (1 + ryc))
            rx, ry = np.ceil(rxc), np.ceil(ryc)
            mx, my = m[:, 0], m[:, 1]
            args = [(mx - rx, np.abs(mx) + rx), (mx + rx, np.abs(mx) + rx),
                    (my - ry, np.abs(my) + ry), (my + ry, np.abs(my) + ry)]
            for v, scale in ((mx + rx, np.abs(mx) + rx), (mx - rx - W, np.abs(mx) + rx + W),
                             (my + ry, np.abs(my) + ry), (my - ry - H, np.abs(my) + ry + H)):
                geom |= np.abs(v) <= band * (1 + scale)
        for v, scale in args:                    # tile rectangle steps, in pixel units
            geom |= TILE_SIZE * _frac_dist(v / TILE_SIZE) <= band * (1 + scale)
        # kinks: frustum clamp and SH clamp
        lnx, lpx, lny, lpy = frustum_limits(cam, prof, np.dtype(np.float64))
        zl = np.where(live, z, 1.0)
        u, v = t[:, 0] / zl, t[:, 1] / zl
        kink = (np.abs(u + lnx) <= bands.kink * lnx) | (np.abs(u - lpx) <= bands.kink * lpx)
        kink |= (np.abs(v + lny) <= bands.kink * lny) | (np.abs(v - lpy) <= bands.kink * lpy)
        deg = out.cache["sh_degree"]
        sh = eval_sh_colors(np.asarray(g.means, np.float64), np.asarray(g.sh, np.float64),
                            cam.center, deg)
        nb = sh["basis"].shape[1]
        rgb = np.einsum("nk,nkc->nc", sh["basis"], np.asarray(g.sh, np.float64)[:, :nb]) + 0.5
        kink |= np.any(np.abs(rgb) <= bands.kink, axis=-1)
    return {"geom": geom & live & ~near, "near": near, "kink": kink & out.visible}


def _mark_reach(mask, out, gs):
    """Mark pixels where any Gaussian of ``gs`` has o G >= 1/255 (1 - 1e-3), in a window of its
    3.33-sigma box plus one tile (clipped to the image)."""
    H, W = mask.shape
    for k in gs:
        mx, my = (float(x) for x in out.means2d[k])
        a, _, c = (float(x) for x in out.cov2d[k])
        A, B, C = (float(x) for x in out.conics[k])
        o = float(out.opacities[k])
        if not (np.isfinite(mx) and np.isfinite(my) and o > 0):
            continue
        rx = 3.33 * math.sqrt(max(a, 0.0)) + TILE_SIZE
        ry = 3.33 * math.sqrt(max(c, 0.0)) + TILE_SIZE
        j0, j1 = int(max(0, math.floor(mx - rx))), int(min(W, math.ceil(mx + rx)))
        i0, i1 = int(max(0, math.floor(my - ry))), int(min(H, math.ceil(my + ry)))
        if j0 >= j1 or i0 >= i1:
            continue
        dx = mx - (np.arange(j0, j1) + 0.5)[None, :]
        dy = my - (np.arange(i0, i1) + 0.5)[:, None]
        power = -0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy
        mask[i0:i1, j0:j1] |= o * np.exp(np.minimum(power, 0)) >= ALPHA_MIN * (1 - 1e-3)


def find_ties(out, bands: TieBands = FLOAT32_BANDS) -> dict:
    """Near-ties of ``out`` = refgs.fast.render of float64 Gaussians (module docstring).

    Returns ``forward`` (H,W) bool (alpha | stop | depth | geom), ``backward`` (H,W) bool
    (forward | cap for gsplat), ``kink_gaussians`` (N,) bool, and ``counts`` of pixels (or
    Gaussians) per reason.
    """
    if out.image.dtype != np.float64:
        raise ValueError("find_ties: expected a float64 render of refgs.fast.render, "
                         f"got {out.image.dtype}")
    c = out.cache
    prof = c["profile"]
    H, W = out.alpha.shape
    gx, gy = tile_grid(W, H)
    gt = gaussian_ties(out, bands)
    gtie = gt["geom"] | gt["near"]
    d = {k: np.empty((H, W)) for k in ("alpha", "stop", "cap", "depth")}
    hit = np.zeros((H, W), bool)
    _pixel_distances(0, gx * gy, c["lists"]["gauss"], c["lists"]["offsets"], out.means2d,
                     out.conics, out.opacities, out.colors, out.depths, c["rc"],
                     float(np.finfo(np.float64).eps),
                     bool(prof.stop_inclusive), gx, gtie, d["alpha"], d["stop"], d["cap"],
                     d["depth"], hit)
    per = {"alpha": d["alpha"] <= bands.alpha, "stop": d["stop"] <= bands.stop,
           "depth": d["depth"] <= bands.depth}
    geom = hit.copy()
    _mark_reach(geom, out, np.flatnonzero(gtie))
    if np.any(gt["near"]):
        geom[:] = True                           # a near/far-plane tie: everything is suspect
    per["geom"] = geom
    fwd = per["alpha"] | per["stop"] | per["depth"] | per["geom"]
    cap = (d["cap"] <= bands.cap) if not prof.grad_through_alpha_cap else np.zeros((H, W), bool)
    per["cap"] = cap
    counts = {k: int(v.sum()) for k, v in per.items()}
    counts["geom_gaussians"] = int(gtie.sum())
    counts["kink_gaussians"] = int(gt["kink"].sum())
    return {"forward": fwd, "backward": fwd | cap, "kink_gaussians": gt["kink"], "counts": counts}
