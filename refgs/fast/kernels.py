"""Tile lists and per-pixel front-to-back compositing, forward and backward, as numba kernels.

Same model as refgs.rasterize (RAS-01..RAS-10, PRF-05..PRF-07); the loop is the literal per-pixel
loop of the spec instead of the reference's batched cumprod:

* :func:`build_tile_lists` -- every tile's list of covering Gaussians sorted by depth, ties by
  Gaussian index (RAS-01, RAS-02): the visible Gaussians are sorted once (a stable argsort by
  depth, done by the caller) and dealt to the tiles of their rectangles in that order (a counting
  sort), so each list comes out sorted.  O(N log N + P) for P intersections.
* :func:`composite_forward` -- over a range of tiles; every pixel sees its tile's list front to
  back: power (skip > 0), alpha = min(cap, o G) (skip < 1/255), the profile's stop rule on
  T (1 - alpha) with the saturating Gaussian not blended, colour / depth accumulation, T_final and
  n_contrib (1-based list position of the last blended Gaussian).  The loops run per pixel row
  with the list slot outside and the row's pixels inside (each pixel keeps its own T, colour,
  depth, done flag), which is the per-pixel front-to-back order of the spec for every pixel.
* :func:`composite_backward` -- over a range of tiles; per pixel row the forward is *replayed* over
  list positions 1..n_contrib to recover T_i and alpha_i of every blended fragment (the same
  products in the same order as the forward, so T_i is bit-identical to the forward's, unlike the
  original's division T_i = T_{i+1} / (1 - alpha_i)), then each pixel's blended fragments are
  walked back to front with the suffix sum of RAS-07.  Each tile sums its pixels' contributions
  per list slot (pixel order fixed) and writes them to a buffer row per intersection;
  :func:`reduce_by_gaussian` then adds the rows into per-Gaussian gradients sequentially in
  intersection order.  No atomics, no races: the result is bit-identical for any thread count and
  any split of the tiles into work items.

Screen (RAS-09: an implementation device, not part of the model).  Per tile, for each list slot
and each of the 16 pixel rows, the columns where alpha could reach 1/255 are the chord of the
ellipse d^T conic d <= q' with q' = 2 ln(255 o) widened by a bound on the rounding error of the
computed power (SCREEN_ULPS eps |terms|) plus SCREEN_MARGIN; the chord is solved in float64 and
padded for its own rounding.  A fragment outside its chord has computed o G < 1/255 by at least a
factor exp(-SCREEN_MARGIN / 2), so skipping it changes nothing; fragments inside are evaluated
exactly as the spec says.  Non-positive-definite conics and non-finite values get no screen.
Each row then walks only its slots (in list order) and, for each, only the pixels of its chord.
``screen=False`` evaluates every (pixel, slot) pair; the outputs are bit-identical
(tests/test_fast.py checks this).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..constants import ALPHA_MIN, TILE_SIZE

#: extra width of the screen in units of the quadratic form (= 2 x log units; our choice: float32
#: rounding of o*exp(power) is ~1e-7 relative, far below exp(-SCREEN_MARGIN / 2) - 1).
SCREEN_MARGIN = 4e-3
#: rounding-error bound of the computed power, in ulps of the dtype times
#: |A| dx^2 + |C| dy^2 + 2 |B| |dx dy| (about 10 roundings occur; 64 is generous)
SCREEN_ULPS = 64.0
#: relative rounding bound of the float64 chord computation (a few float64 ulps, generous)
_F64_ULPS = 64.0 * 2.0 ** -52
#: absolute padding of a chord, in pixels
_CHORD_PAD = 1e-6
_ALPHA_MIN64 = float(ALPHA_MIN)

# indices of the compositing constants array (in the Gaussians' dtype)
R_ZERO, R_ONE, R_NEG_HALF, R_CAP, R_ALPHA_MIN, R_T_MIN = 0, 1, 2, 3, 4, 5
N_RASTER_CONSTANTS = 6
#: columns of the per-intersection / per-Gaussian gradient buffer
G_MX, G_MY, G_A, G_B, G_C, G_O, G_R, G_G, G_BL, G_Z = range(10)
N_GRAD_COLUMNS = 10


@njit(cache=True, error_model="numpy")
def build_tile_lists(order, rect, n_tiles, gx):
    """Per-tile Gaussian lists in depth order (RAS-01, RAS-02).

    order (V,) int64: visible Gaussians sorted by (depth, index); rect (N,4) int64 (x0,x1,y0,y1),
    max exclusive.  Returns (gauss (P,) int64, offsets (n_tiles+1,) int64): tile t's list is
    gauss[offsets[t]:offsets[t+1]].
    """
    counts = np.zeros(n_tiles, np.int64)
    for g in order:
        for ty in range(rect[g, 2], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 1]):
                counts[ty * gx + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    for t in range(n_tiles):
        offsets[t + 1] = offsets[t] + counts[t]
    cursor = offsets[:-1].copy()
    gauss = np.empty(offsets[n_tiles], np.int64)
    for g in order:
        for ty in range(rect[g, 2], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 1]):
                t = ty * gx + tx
                gauss[cursor[t]] = g
                cursor[t] += 1
    return gauss, offsets


@njit(cache=True, error_model="numpy")
def _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab):
    """The tile's list as a contiguous per-slot table tab[:L] (dtype D): mx, my, A, B, C, o,
    r, g, b, z."""
    for s in range(L):
        g = gauss[start + s]
        tab[s, 0] = means2d[g, 0]
        tab[s, 1] = means2d[g, 1]
        tab[s, 2] = conics[g, 0]
        tab[s, 3] = conics[g, 1]
        tab[s, 4] = conics[g, 2]
        tab[s, 5] = opac[g]
        tab[s, 6] = colors[g, 0]
        tab[s, 7] = colors[g, 1]
        tab[s, 8] = colors[g, 2]
        tab[s, 9] = depths[g]


@njit(cache=True, error_model="numpy")
def _row_tables(tile, start, L, row_cnt, row_slots, row_lo, row_hi):
    """Views of tile ``tile``'s screen tables: cnt (16,), slots / lo / hi (16, L)."""
    a, b = TILE_SIZE * start, TILE_SIZE * (start + L)
    return (row_cnt[tile], row_slots[a:b].reshape((TILE_SIZE, L)),
            row_lo[a:b].reshape((TILE_SIZE, L)), row_hi[a:b].reshape((TILE_SIZE, L)))


@njit(cache=True, error_model="numpy")
def _max_len(offsets, lo, hi):
    """Longest tile list among tiles [lo, hi) (sizes the per-call scratch)."""
    m = 0
    for t in range(lo, hi):
        m = max(m, offsets[t + 1] - offsets[t])
    return m


@njit(cache=True, error_model="numpy")
def _chords(tab, L, xs, ys, eps, screen, cnt, rs, lo, hi):
    """Per pixel row r: the slots that may reach alpha >= 1/255 somewhere in the row, in list
    order (rs[r, :cnt[r]]), with their candidate columns lo..hi (module docstring, Screen).
    cnt (16,), rs / lo / hi (16, >= L) are caller-owned scratch."""
    T = TILE_SIZE
    cnt[:] = 0
    x0 = np.float64(xs[0])
    x1 = np.float64(xs[T - 1])
    y0 = np.float64(ys[0])
    y1 = np.float64(ys[T - 1])
    for s in range(L):
        mx, my = np.float64(tab[s, 0]), np.float64(tab[s, 1])
        A, B, C = np.float64(tab[s, 2]), np.float64(tab[s, 3]), np.float64(tab[s, 4])
        o = np.float64(tab[s, 5])
        det = A * C - B * B
        if screen and o == 0.0:
            continue                                      # alpha = 0 everywhere
        dxm = max(abs(mx - x0), abs(mx - x1))
        dym = max(abs(my - y0), abs(my - y1))
        terms = abs(A) * dxm * dxm + abs(C) * dym * dym + 2.0 * abs(B) * dxm * dym
        q = 2.0 * math.log(o / _ALPHA_MIN64) + SCREEN_ULPS * eps * terms + SCREEN_MARGIN
        # no screen when switched off, for odd conics and for non-finite bounds
        if not screen or not (A > 0.0 and C > 0.0 and det > 0.0 and math.isfinite(det)
                              and math.isfinite(q) and math.isfinite(mx) and math.isfinite(my)):
            for r in range(T):
                k = cnt[r]
                rs[r, k] = s
                lo[r, k] = 0
                hi[r, k] = T - 1
                cnt[r] = k + 1
            continue
        if not q > 0.0:
            continue                                      # o G < 1/255 everywhere
        # rows where the chord can be non-empty: dy^2 (det - F (AC + B^2)) <= A q (1 + F)
        den = det - _F64_ULPS * (A * C + B * B)
        r_lo, r_hi = 0, T - 1
        if den > 0.0:
            dy_max = math.sqrt(A * q * (1.0 + _F64_ULPS) / den) * (1.0 + _F64_ULPS) + _CHORD_PAD
            ylo = my - dy_max - y0
            yhi = my + dy_max - y0
            if yhi < 0.0 or ylo > T - 1.0:
                continue
            r_lo = 0 if ylo <= 0.0 else int(math.ceil(ylo))
            r_hi = T - 1 if yhi >= T - 1.0 else int(math.floor(yhi))
        inv_a = 1.0 / A
        b_a = B * inv_a
        a_q = A * q
        ac_b2 = A * C + B * B
        for r in range(r_lo, r_hi + 1):
            dy = my - np.float64(ys[r])
            dy2 = dy * dy
            disc = a_q - det * dy2 + _F64_ULPS * (a_q + ac_b2 * dy2)
            if disc < 0.0:
                continue
            # d = mean - pixel in [(-B dy - sq) / A, (-B dy + sq) / A]  =>  pixel centre within
            # half of mx + B dy / A, padded for the rounding of this float64 arithmetic
            half = math.sqrt(disc) * inv_a
            centre = mx + b_a * dy
            pad = _F64_ULPS * (abs(b_a * dy) + half + abs(mx)) + _CHORD_PAD
            plo = centre - half - pad - x0
            phi = centre + half + pad - x0
            if plo != plo or phi != phi:
                c_lo, c_hi = 0, T - 1                     # NaN: no screen for this row
            else:
                if phi < 0.0 or plo > T - 1.0:
                    continue
                c_lo = 0 if plo <= 0.0 else int(math.ceil(plo))
                c_hi = T - 1 if phi >= T - 1.0 else int(math.floor(phi))
            if c_lo > c_hi:
                continue
            k = cnt[r]
            rs[r, k] = s
            lo[r, k] = c_lo
            hi[r, k] = c_hi
            cnt[r] = k + 1


@njit(cache=True, inline="always", error_model="numpy")
def _power(A, B, Cdy2, dx, dy, neg_half):
    """-0.5 (A dx^2 + C dy^2) - B dx dy with d = mean - pixel (RAS-03), C dy^2 precomputed per row
    (the same operations, in the same order, as refgs.rasterize)."""
    return neg_half * (A * dx * dx + Cdy2) - B * dx * dy


@njit(cache=True, error_model="numpy")
def _centres(origin, like):
    """Pixel centres origin + k + 0.5, k = 0..15 (CNV-08), in the dtype of ``like``."""
    c = np.empty(TILE_SIZE, like.dtype)
    for k in range(TILE_SIZE):
        c[k] = origin + k + 0.5
    return c


@njit(cache=True, nogil=True, error_model="numpy")
def composite_forward(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc, eps,
                      stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib, final_T,
                      row_cnt, row_slots, row_lo, row_hi):
    """Front-to-back compositing (RAS-03..RAS-06) of the pixels of tiles [lo, hi).

    gauss/offsets from :func:`build_tile_lists`; per-Gaussian means2d (N,2), conics (N,3),
    opac (N,), colors (N,3), depths (N,); bg (3,), rc the R_* constants, eps the dtype's machine
    epsilon (float64); outputs image (H,W,3), alpha_img / depth_img / final_T (H,W) in D,
    n_contrib (H,W) int32, written for these tiles only.  The screen's row lists are kept for the
    backward: row_cnt (n_tiles, 16) int64 and, for tile t with list length L, row_slots / row_lo /
    row_hi (16 P,) hold its (16, L) tables at [16 offsets[t], 16 offsets[t+1]).
    """
    H, W = alpha_img.shape
    one, zero, t_min = rc[R_ONE], rc[R_ZERO], rc[R_T_MIN]
    neg_half, cap, amin = rc[R_NEG_HALF], rc[R_CAP], rc[R_ALPHA_MIN]
    dt = means2d.dtype
    Lm = _max_len(offsets, lo, hi)
    tab = np.empty((Lm, 10), dt)
    T = np.empty(TILE_SIZE, dt)
    acc = np.empty((TILE_SIZE, 4), dt)          # colour r, g, b and depth per pixel of the row
    last = np.empty(TILE_SIZE, np.int32)
    done = np.empty(TILE_SIZE, np.bool_)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = _centres(tx * TILE_SIZE, tab)
        ys = _centres(ty * TILE_SIZE, tab)
        cnt, rs, col_lo, col_hi = _row_tables(tile, start, L, row_cnt, row_slots, row_lo, row_hi)
        _chords(tab, L, xs, ys, eps, screen, cnt, rs, col_lo, col_hi)
        ncols = min(TILE_SIZE, W - tx * TILE_SIZE)
        for r in range(TILE_SIZE):
            i = ty * TILE_SIZE + r
            if i >= H:
                break
            py = ys[r]
            T[:] = one
            acc[:, :] = zero
            last[:] = 0
            done[:] = False
            n_done = 0
            for k in range(cnt[r]):
                s = rs[r, k]
                mx, A, B, o = tab[s, 0], tab[s, 2], tab[s, 3], tab[s, 5]
                dy = tab[s, 1] - py
                Cdy2 = tab[s, 4] * dy * dy
                cr, cg, cb, z = tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                for c in range(col_lo[r, k], min(col_hi[r, k] + 1, ncols)):
                    if done[c]:
                        continue
                    power = _power(A, B, Cdy2, mx - xs[c], dy, neg_half)
                    if power > zero:                     # RAS-03
                        continue
                    a = min(cap, o * math.exp(power))    # RAS-04
                    if a < amin:
                        continue
                    Tc = T[c]
                    test_T = Tc * (one - a)
                    if (test_T <= t_min) if stop_inclusive else (test_T < t_min):
                        done[c] = True                   # RAS-05: this fragment is not blended
                        n_done += 1
                        continue
                    w = a * Tc
                    acc[c, 0] += cr * w
                    acc[c, 1] += cg * w
                    acc[c, 2] += cb * w
                    acc[c, 3] += z * w
                    T[c] = test_T
                    last[c] = s + 1
                if n_done == ncols:
                    break
            for c in range(ncols):
                j = tx * TILE_SIZE + c
                image[i, j, 0] = acc[c, 0] + T[c] * bg[0]
                image[i, j, 1] = acc[c, 1] + T[c] * bg[1]
                image[i, j, 2] = acc[c, 2] + T[c] * bg[2]
                alpha_img[i, j] = one - T[c]
                depth_img[i, j] = acc[c, 3]
                n_contrib[i, j] = last[c]
                final_T[i, j] = T[c]


@njit(cache=True, nogil=True, error_model="numpy")
def composite_backward(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                       grad_through_cap, gx, n_contrib, final_T, v_image, v_alpha, v_depth,
                       row_cnt, row_slots, row_lo, row_hi, contrib):
    """Backward of :func:`composite_forward` (RAS-07, RAS-08, RAS-10) for tiles [lo, hi).

    For the blended fragments of a pixel (T_i before fragment i, w_i = a_i T_i,
    cv_i = c_i . v_image + z_i v_depth):

      v_c_i = w_i v_image,  v_z_i = w_i v_depth,
      v_a_i = T_i cv_i - (sum_{j behind i} w_j cv_j + T_final (bg . v_image - v_alpha)) / (1 - a_i),

    then a = min(cap, o G) (inria: gradient through the cap; gsplat: none where o G > cap),
    v_power = o G v_oG and the conic / 2D-mean gradients with the off-diagonal counted once.

    One walk back to front per pixel, from list position n_contrib: every valid fragment there
    was blended, and T_i = T_{i+1} / (1 - a_i) starting from T_final (the original's recovery,
    computed as T_{i+1} * (1 / (1 - a_i)); the forward's T_{i+1} = T_i (1 - a_i) used the same
    rounded 1 - a_i, so each step adds about three roundings: relative error <~ 3 n eps after n
    fragments -- ~1e-14 in float64, and in float32 ~2e-5 at worst for the ~100 fragments of a
    saturated pixel, typically far less because the roundings do not all add up).  The row tables are the
    forward's (row_cnt, row_slots, row_lo, row_hi).
    Writes contrib (P, 10): row offsets[t] + s = the sum over tile t's pixels for list slot s
    (pixel rows in order, the row's pixels left to right), columns G_* (means2d x, y; conic A, B,
    C; opacity; colour r, g, b; depth).
    """
    H, W = final_T.shape
    one, zero, neg_half, cap = rc[R_ONE], rc[R_ZERO], rc[R_NEG_HALF], rc[R_CAP]
    amin = rc[R_ALPHA_MIN]
    dt = means2d.dtype
    Lm = _max_len(offsets, lo, hi)
    tab = np.empty((Lm, 10), dt)
    acc = np.empty((Lm, 10), dt)
    last = np.empty(TILE_SIZE, np.int64)
    T = np.empty(TILE_SIZE, dt)
    suffix = np.empty(TILE_SIZE, dt)
    tail = np.empty(TILE_SIZE, dt)
    vpix = np.empty((TILE_SIZE, 4), dt)             # v_image r, g, b and v_depth per pixel
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = _centres(tx * TILE_SIZE, tab)
        ys = _centres(ty * TILE_SIZE, tab)
        cnt, rs, col_lo, col_hi = _row_tables(tile, start, L, row_cnt, row_slots, row_lo, row_hi)
        acc[:L, :] = zero
        ncols = min(TILE_SIZE, W - tx * TILE_SIZE)
        for r in range(TILE_SIZE):
            i = ty * TILE_SIZE + r
            if i >= H:
                break
            py = ys[r]
            max_last = 0
            for c in range(ncols):
                j = tx * TILE_SIZE + c
                last[c] = n_contrib[i, j]
                max_last = max(max_last, last[c])
                T[c] = final_T[i, j]
                suffix[c] = zero
                vpix[c, 0], vpix[c, 1], vpix[c, 2] = v_image[i, j, 0], v_image[i, j, 1], v_image[i, j, 2]
                vpix[c, 3] = v_depth[i, j]
                tail[c] = final_T[i, j] * (vpix[c, 0] * bg[0] + vpix[c, 1] * bg[1] + vpix[c, 2] * bg[2]
                                           - v_alpha[i, j])
            for k in range(cnt[r] - 1, -1, -1):           # back to front
                s = rs[r, k]
                if s >= max_last:
                    continue
                mx, A, B, C, o = tab[s, 0], tab[s, 2], tab[s, 3], tab[s, 4], tab[s, 5]
                dy = tab[s, 1] - py
                Cdy2 = C * dy * dy
                cr, cg, cb, z = tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                g_mx = g_my = g_a = g_b = g_c = g_o = g_r = g_g = g_bl = g_z = zero
                for c in range(col_lo[r, k], min(col_hi[r, k] + 1, ncols)):
                    if s >= last[c]:
                        continue
                    dx = mx - xs[c]
                    power = _power(A, B, Cdy2, dx, dy, neg_half)
                    if power > zero:
                        continue
                    G = math.exp(power)
                    oG = o * G
                    a = min(cap, oG)
                    if a < amin:
                        continue
                    inv = one / (one - a)
                    Ti = T[c] * inv                         # T before this fragment
                    T[c] = Ti
                    cv = cr * vpix[c, 0] + cg * vpix[c, 1] + cb * vpix[c, 2] + z * vpix[c, 3]
                    w = a * Ti
                    v_a = Ti * cv - (suffix[c] + tail[c]) * inv
                    suffix[c] += w * cv
                    v_oG = v_a if (grad_through_cap or oG <= cap) else zero     # RAS-10
                    v_pow = v_oG * o * G
                    g_mx += -(A * dx + B * dy) * v_pow
                    g_my += -(C * dy + B * dx) * v_pow
                    g_a += neg_half * dx * dx * v_pow
                    g_b += -dx * dy * v_pow                                   # RAS-08
                    g_c += neg_half * dy * dy * v_pow
                    g_o += v_oG * G
                    g_r += w * vpix[c, 0]
                    g_g += w * vpix[c, 1]
                    g_bl += w * vpix[c, 2]
                    g_z += w * vpix[c, 3]
                acc[s, G_MX] += g_mx
                acc[s, G_MY] += g_my
                acc[s, G_A] += g_a
                acc[s, G_B] += g_b
                acc[s, G_C] += g_c
                acc[s, G_O] += g_o
                acc[s, G_R] += g_r
                acc[s, G_G] += g_g
                acc[s, G_BL] += g_bl
                acc[s, G_Z] += g_z
        for s in range(L):
            for q in range(10):
                contrib[start + s, q] = acc[s, q]


@njit(cache=True, error_model="numpy")
def reduce_by_gaussian(gauss, contrib, out):
    """out[g] += contrib[p] for every intersection p of Gaussian g = gauss[p], sequentially in
    intersection order (a fixed-order, race-free reduction).  out (N, 10) zero-initialised."""
    for p in range(gauss.size):
        g = gauss[p]
        for k in range(contrib.shape[1]):
            out[g, k] += contrib[p, k]
