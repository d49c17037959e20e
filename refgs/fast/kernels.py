"""Tile lists and per-pixel front-to-back compositing, forward and backward, as numba kernels.

Same model as refgs.rasterize (RAS-01..RAS-10, PRF-05..PRF-07); the loop is the literal per-pixel
loop of the spec instead of the reference's batched cumprod:

* :func:`build_tile_lists` -- every tile's list of covering Gaussians sorted by depth, ties by
  Gaussian index (RAS-01, RAS-02): the visible Gaussians are sorted once (a stable argsort by
  depth, done by the caller) and dealt to the tiles of their rectangles in that order (a counting
  sort), so each list comes out sorted.  O(N log N + P) for P intersections.  Only *live*
  intersections are dealt (:func:`tile_alive`: tiles where the screen below can keep the
  Gaussian in some pixel row; on trained fern models 1/4 of the 3-sigma rectangles' tiles),
  each with its position in the full list (``pos``), so n_contrib still counts the spec's lists.
* :func:`composite_forward` -- over a range of tiles; every pixel sees its tile's list front to
  back: power (skip > 0), alpha = min(cap, o G) (skip < 1/255), the profile's stop rule on
  T (1 - alpha) with the saturating Gaussian not blended, colour / depth accumulation, T_final and
  n_contrib (1-based list position of the last blended Gaussian).  The loops run per pixel row
  with the list slot outside and the row's pixels inside (each pixel keeps its own T, colour,
  depth, done flag), which is the per-pixel front-to-back order of the spec for every pixel.
  The row's 16 pixels are 16 *lanes* computed without branches (every test a mask, every update
  a select), so LLVM turns the lane loop into SIMD code; exp is refgs.fast.fexp.fast_exp
  (within 1 ulp of exp; ``math.exp`` is a scalar library call that stops vectorisation).
* :func:`composite_backward` -- over a range of tiles; each pixel's blended fragments are walked
  back to front from list position n_contrib, T_i recovered from T_final by division as the
  original does (T_i = T_{i+1} * (1 / (1 - alpha_i)); docs/fast.md, "T recovery"), and
  the suffix sum of RAS-07 (16 masked lanes, as in the forward).  Each
  tile sums its pixels' contributions per list slot in a fixed order -- per lane pair (c, c + 8)
  over the rows, then the 8 pair sums in lane order -- and writes them to a buffer row per
  intersection;
  :func:`reduce_by_gaussian` then adds the rows into per-Gaussian gradients in intersection
  order (threads split the Gaussians, not the intersections).  No atomics, no races: the result
  is bit-identical for any thread count and any split of the tiles into work items.

Screen (RAS-09: an implementation device, not part of the model).  Per tile, for each list slot
and each of the 16 pixel rows, the columns where alpha could reach 1/255 are the chord of the
ellipse d^T conic d <= q' with q' = 2 ln(255 o) widened by a bound on the rounding error of the
computed power (SCREEN_ULPS eps |terms|) plus SCREEN_MARGIN; the chord is solved in float64 and
padded for its own rounding.  A fragment outside its chord has computed o G < 1/255 by at least a
factor exp(-SCREEN_MARGIN / 2), so skipping it changes nothing; fragments inside are evaluated
exactly as the spec says.  Non-positive-definite conics and non-finite values get no screen.
The compositing kernels keep, per row, the slots whose chord contains a pixel centre of the row
(:func:`_row_lists`) and walk only those, in list order, all 16 lanes of the row at once (the
lanes outside the chord fail the alpha test by the bound above; :func:`_chords` keeps the
columns too, for refgs.fast.ties).  Before any tile is composited, :func:`tile_alive` applies the
same bound per Gaussian and tile of its rectangle, conservatively (q at its largest over the
rectangle, every bound widened), so a tile list leaves out only Gaussians the screen would skip
in every row of that tile: no output changes, and the compositing no longer gathers and screens
them (tests/test_fast.py::test_live_intersections_contain_every_slot_the_screen_keeps).  ``screen=False`` evaluates every (pixel, slot) pair; the outputs are bit-identical
(tests/test_fast.py checks this).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..constants import ALPHA_MIN, TILE_SIZE
from .fexp import fast_exp

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
#: lane offsets of the forward's per-row state array (T, colour r, g, b, depth, done flag)
_S_T, _S_R, _S_G, _S_B, _S_Z, _S_DONE = (k * TILE_SIZE for k in range(6))
_N_STATE = 6
#: lane offsets of the backward's per-row state array
_B_T, _B_SUF, _B_TAIL, _B_VR, _B_VG, _B_VB, _B_VZ = (k * TILE_SIZE for k in range(7))
_N_BSTATE = 7
_HALF = TILE_SIZE // 2
_NT_HALF = N_GRAD_COLUMNS * _HALF
#: columns of a tile's per-slot table (:func:`_gather`)
N_TAB = 12


@njit(cache=True, nogil=True, error_model="numpy")
def merge_runs(keys, a, b, out):
    """Stable merge of two index runs a, b (each sorted by keys[.], stably) into out, taking
    from a on equal keys: when every index of a precedes every index of b this is the stable
    order of a and b together (the depth order of RAS-02).  keys must be free of NaN."""
    i = j = k = 0
    na, nb = a.size, b.size
    while i < na and j < nb:
        if keys[b[j]] < keys[a[i]]:
            out[k] = b[j]
            j += 1
        else:
            out[k] = a[i]
            i += 1
        k += 1
    while i < na:
        out[k] = a[i]
        i += 1
        k += 1
    while j < nb:
        out[k] = b[j]
        j += 1
        k += 1


@njit(cache=True, nogil=True, error_model="numpy")
def tile_counts(lo, hi, order, rect, rect_off, live, gx, counts):
    """counts[t] = number of Gaussians of ``order`` whose tile rectangle holds tile t and that are
    live there (``live``, :func:`tile_alive`), for the tiles of tile rows lo..hi (the first pass
    of :func:`build_tile_lists`)."""
    for k in range(order.size):
        g = order[k]
        x0, x1, y0 = rect[g, 0], rect[g, 1], rect[g, 2]
        for ty in range(max(lo, y0), min(hi, rect[g, 3])):
            base = rect_off[k] + (ty - y0) * (x1 - x0) - x0
            for tx in range(x0, x1):
                if live[base + tx]:
                    counts[ty * gx + tx] += 1


@njit(cache=True, nogil=True, error_model="numpy")
def tile_fill(lo, hi, order, rect, rect_off, live, gx, cursor, full, gauss, pos):
    """The second pass for tile rows lo..hi: each Gaussian of ``order``, in that order, appended
    to the lists of the tiles where it is live (cursor[t]: next free position of tile t's list),
    with pos = its position in the tile's full list (every Gaussian whose rectangle holds the
    tile, live or not; full[t] counts them), which is what n_contrib reports (RAS-06)."""
    for k in range(order.size):
        g = order[k]
        x0, x1, y0 = rect[g, 0], rect[g, 1], rect[g, 2]
        for ty in range(max(lo, y0), min(hi, rect[g, 3])):
            base = rect_off[k] + (ty - y0) * (x1 - x0) - x0
            for tx in range(x0, x1):
                t = ty * gx + tx
                if live[base + tx]:
                    gauss[cursor[t]] = g
                    pos[cursor[t]] = full[t]
                    cursor[t] += 1
                full[t] += 1


@njit(cache=True, nogil=True, error_model="numpy")
def rect_offsets(order, rect, out):
    """out (V+1,) = prefix sums of the tile counts of the rectangles of order's Gaussians: where
    each rectangle's tiles start in the per-intersection ``live`` array (row-major)."""
    out[0] = 0
    for k in range(order.size):
        g = order[k]
        out[k + 1] = out[k] + max(rect[g, 1] - rect[g, 0], 0) * max(rect[g, 3] - rect[g, 2], 0)


#: relative and absolute (pixels) widening of :func:`tile_alive`'s bounds: far above the
#: float64 rounding of its own arithmetic and of the screen's (_F64_ULPS, _CHORD_PAD), so that
#: its live set contains every slot the screen keeps; pixel centres are 1 px apart, so the
#: widening costs nothing measurable.
_LIVE_REL = 1e-9
_LIVE_PAD = 1e-3


@njit(cache=True, nogil=True, error_model="numpy")
def tile_alive(lo, hi, order, rect, rect_off, means2d, conics, opac, eps, live):
    """For the Gaussians order[lo:hi]: live[rect_off[k] + (ty - y0) (x1 - x0) + (tx - x0)] for
    each tile (tx, ty) of the rectangle of Gaussian order[k].

    Conservative: a tile is live unless no pixel centre of it can lie inside the screen's
    ellipse d^T conic d <= q (module docstring, Screen), with q taken at its largest over the
    rectangle (the rounding term grows with the distance to the mean) and every bound widened by
    _LIVE_REL / _LIVE_PAD; so every slot that :func:`_row_lists` keeps in some row is live, and a
    slot that is not live has o G < 1/255 at every pixel centre of the tile: leaving it out of
    the tile's list changes no output (the forward's screen then drops the live slots it does not
    keep, as before).  Per tile row, the ellipse's x-range over the row's pixel-centre band is the
    range of the chord ends mx + (B/A) dy +- sqrt(A q - det dy^2) / A, at their extremes
    dy = +-B sqrt(q / (det C)) clamped to the band (d = mean - pixel, dy = my - py).  Odd or
    non-finite conics are live everywhere (the screen's _ALL_ROWS)."""
    T = TILE_SIZE
    for k in range(lo, hi):
        g = order[k]
        rx0, rx1, ry0, ry1 = rect[g, 0], rect[g, 1], rect[g, 2], rect[g, 3]
        base = rect_off[k]
        w = rx1 - rx0
        mx, my = np.float64(means2d[g, 0]), np.float64(means2d[g, 1])
        A, B, C = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        o = np.float64(opac[g])
        det = A * C - B * B
        # q at its largest over the rectangle's pixel centres (the screen's q per tile is <= this)
        dxm = max(abs(mx - (rx0 * T + 0.5)), abs(mx - (rx1 * T - 0.5)))
        dym = max(abs(my - (ry0 * T + 0.5)), abs(my - (ry1 * T - 0.5)))
        terms = abs(A) * dxm * dxm + abs(C) * dym * dym + 2.0 * abs(B) * dxm * dym
        q = (_log_term(o) + SCREEN_ULPS * eps * terms + SCREEN_MARGIN) * (1.0 + _LIVE_REL) + _LIVE_REL
        odd = not (A > 0.0 and C > 0.0 and det > 0.0 and math.isfinite(det) and math.isfinite(q)
                   and math.isfinite(mx) and math.isfinite(my))
        if odd or not (o > 0.0 and q > 0.0):
            for i in range(base, base + w * (ry1 - ry0)):
                live[i] = odd                            # o G < 1/255 everywhere when not odd
            continue
        ey = math.sqrt(q * A / det) * (1.0 + _LIVE_REL) + _LIVE_PAD       # |dy| on the ellipse
        b_a = B / A
        dys = B * math.sqrt(q / (det * C))               # where the chord's right end peaks
        for ty in range(ry0, ry1):
            row = base + (ty - ry0) * w - rx0
            lo_dy = max(my - (ty * T + (T - 1) + 0.5), -ey)      # dy over the row band
            hi_dy = min(my - (ty * T + 0.5), ey)
            x_lo, x_hi = 1.0, 0.0                        # empty
            if lo_dy <= hi_dy:
                d1 = min(max(dys, lo_dy), hi_dy)
                d2 = min(max(-dys, lo_dy), hi_dy)
                h1 = math.sqrt(max(A * q - det * d1 * d1, 0.0)) / A
                h2 = math.sqrt(max(A * q - det * d2 * d2, 0.0)) / A
                x_hi = mx + b_a * d1 + h1
                x_lo = mx + b_a * d2 - h2
                pad = _LIVE_REL * (abs(mx) + abs(b_a) * ey + h1 + h2) + _LIVE_PAD
                x_hi += pad
                x_lo -= pad
            for tx in range(rx0, rx1):
                # the tile's pixel centres tx T + 0.5 .. tx T + 15.5 against [x_lo, x_hi]
                live[row + tx] = (x_lo <= tx * T + (T - 1) + 0.5) & (x_hi >= tx * T + 0.5)


@njit(cache=True, error_model="numpy")
def build_tile_lists(order, rect, n_tiles, gx, rect_off, live):
    """Per-tile Gaussian lists in depth order (RAS-01, RAS-02), of the live intersections.

    order (V,) int64: visible Gaussians sorted by (depth, index); rect (N,4) int64 (x0,x1,y0,y1),
    max exclusive; rect_off (V+1,) int64: start of order[k]'s rectangle in ``live`` (row-major),
    live (rect_off[V],) bool (all True: the full lists of the spec).  Returns (gauss (P,) int64,
    offsets (n_tiles+1,) int64, pos (P,) int32): tile t's list is gauss[offsets[t]:offsets[t+1]],
    pos the positions in the full lists.  (refgs.fast.render runs the passes over bands of tile
    rows in parallel, with the same result.)
    """
    gy = n_tiles // gx
    counts = np.zeros(n_tiles, np.int64)
    tile_counts(0, gy, order, rect, rect_off, live, gx, counts)
    offsets = np.zeros(n_tiles + 1, np.int64)
    for t in range(n_tiles):
        offsets[t + 1] = offsets[t] + counts[t]
    cursor = offsets[:-1].copy()
    full = np.zeros(n_tiles, np.int64)
    gauss = np.empty(offsets[n_tiles], np.int64)
    pos = np.empty(offsets[n_tiles], np.int32)
    tile_fill(0, gy, order, rect, rect_off, live, gx, cursor, full, gauss, pos)
    return gauss, offsets, pos


@njit(cache=True, error_model="numpy")
def _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab):
    """The tile's list as a contiguous per-slot table tab[:L] (dtype D, N_TAB columns): mx, my,
    A, B, C, o, r, g, b, z, then the residuals mx - D(mx), my - D(my) of the 2D mean.

    means2d is in D, or float64 for float32 compositing of float64 geometry (Mixed precision):
    the mean is then carried as D(m) + D(m - D(m)), about 2 x 24 bits, so that the pixel offset
    d = (mx - px) + residual is accurate to a few ulps of d itself rather than to an ulp of the
    absolute coordinate (~3e-5 px at 500 px in float32).  A mean already in D has residual 0,
    and x + 0 = x: the same results bit for bit."""
    for s in range(L):
        g = gauss[start + s]
        tab[s, 0] = means2d[g, 0]                  # rounded to D on the store
        tab[s, 1] = means2d[g, 1]
        tab[s, 10] = means2d[g, 0] - tab[s, 0]     # exact in float64, then rounded to D
        tab[s, 11] = means2d[g, 1] - tab[s, 1]
        tab[s, 2] = conics[g, 0]
        tab[s, 3] = conics[g, 1]
        tab[s, 4] = conics[g, 2]
        tab[s, 5] = opac[g]
        tab[s, 6] = colors[g, 0]
        tab[s, 7] = colors[g, 1]
        tab[s, 8] = colors[g, 2]
        tab[s, 9] = depths[g]


@njit(cache=True, error_model="numpy")
def _row_tables(tile, start, L, row_cnt, row_slots):
    """Views of tile ``tile``'s row lists: cnt (16,), slots (16, L)."""
    a, b = TILE_SIZE * start, TILE_SIZE * (start + L)
    return row_cnt[tile], row_slots[a:b].reshape((TILE_SIZE, L))


@njit(cache=True, error_model="numpy")
def _max_len(offsets, lo, hi):
    """Longest tile list among tiles [lo, hi) (sizes the per-call scratch)."""
    m = 0
    for t in range(lo, hi):
        m = max(m, offsets[t + 1] - offsets[t])
    return m


#: _slot_screen verdicts
_SKIP, _ALL_ROWS, _SCREENED = 0, 1, 2


@njit(cache=True, inline="always", error_model="numpy")
def _log_term(o):
    """2 ln(o / (1/255)), the opacity part of the screen's bound q (float64; -inf for o = 0)."""
    return 2.0 * math.log(o / _ALPHA_MIN64)


@njit(cache=True, inline="always", error_model="numpy")
def _screen_values(mx, my, A, B, C, o, lg, x0, x1, y0, y1, eps, screen):
    """The screen's per-slot part (module docstring, Screen) on float64 scalars (``lg`` =
    :func:`_log_term` of o), shared by :func:`_chords`, :func:`_row_lists` and
    :func:`tile_alive`: (verdict, det, q, r_lo, r_hi); verdict _SKIP (o G < 1/255 in the whole
    tile), _ALL_ROWS (no screen: switched off, odd conic or non-finite bound) or _SCREENED (rows
    r_lo..r_hi may hold a chord)."""
    T = TILE_SIZE
    det = A * C - B * B
    if screen and o == 0.0:
        return _SKIP, det, 0.0, 0, -1                   # alpha = 0 everywhere
    dxm = max(abs(mx - x0), abs(mx - x1))
    dym = max(abs(my - y0), abs(my - y1))
    terms = abs(A) * dxm * dxm + abs(C) * dym * dym + 2.0 * abs(B) * dxm * dym
    q = lg + SCREEN_ULPS * eps * terms + SCREEN_MARGIN
    if not screen or not (A > 0.0 and C > 0.0 and det > 0.0 and math.isfinite(det)
                          and math.isfinite(q) and math.isfinite(mx) and math.isfinite(my)):
        return _ALL_ROWS, det, q, 0, T - 1
    if not q > 0.0:
        return _SKIP, det, q, 0, -1                     # o G < 1/255 everywhere
    # rows where the chord can be non-empty: dy^2 (det - F (AC + B^2)) <= A q (1 + F)
    den = det - _F64_ULPS * (A * C + B * B)
    r_lo, r_hi = 0, T - 1
    if den > 0.0:
        dy_max = math.sqrt(A * q * (1.0 + _F64_ULPS) / den) * (1.0 + _F64_ULPS) + _CHORD_PAD
        ylo = my - dy_max - y0
        yhi = my + dy_max - y0
        if yhi < 0.0 or ylo > T - 1.0:
            return _SKIP, det, q, 0, -1
        r_lo = 0 if ylo <= 0.0 else int(math.ceil(ylo))
        r_hi = T - 1 if yhi >= T - 1.0 else int(math.floor(yhi))
    return _SCREENED, det, q, r_lo, r_hi


@njit(cache=True, inline="always", error_model="numpy")
def _slot_screen(tab, s, x0, x1, y0, y1, eps, screen):
    """:func:`_screen_values` of list slot s of a tile's table: (verdict, mx, my, A, B, C, det, q,
    r_lo, r_hi) in float64."""
    mx = np.float64(tab[s, 0]) + np.float64(tab[s, 10])     # the mean the lanes see
    my = np.float64(tab[s, 1]) + np.float64(tab[s, 11])
    A, B, C = np.float64(tab[s, 2]), np.float64(tab[s, 3]), np.float64(tab[s, 4])
    o = np.float64(tab[s, 5])
    verdict, det, q, r_lo, r_hi = _screen_values(mx, my, A, B, C, o, _log_term(o), x0, x1, y0, y1,
                                                 eps, screen)
    return verdict, mx, my, A, B, C, det, q, r_lo, r_hi


@njit(cache=True, inline="always", error_model="numpy")
def _rows_keep(mx, my, A, B, C, det, q, x0, ys, r_lo, r_hi, keep):
    """keep[r] (16,) = whether the screen's chord of row r (pixel centre ys[r]) holds a pixel
    centre of the tile (columns x0 .. x0 + 15), for a _SCREENED slot; computed for all 16 rows at
    once (vectorised), False outside r_lo..r_hi.  Shared by :func:`_row_lists` and
    :func:`tile_alive`, so both take the same decisions."""
    T = TILE_SIZE
    top = T - 1.0
    inv_a = 1.0 / A
    b_a = B * inv_a
    a_q = A * q
    ac_b2 = A * C + B * B
    for r in range(T):
        dy = my - np.float64(ys[r])
        dy2 = dy * dy
        disc = a_q - det * dy2 + _F64_ULPS * (a_q + ac_b2 * dy2)
        half = math.sqrt(0.0 if disc < 0.0 else disc) * inv_a
        centre = mx + b_a * dy
        pad = _F64_ULPS * (abs(b_a * dy) + half + abs(mx)) + _CHORD_PAD
        plo = centre - half - pad - x0
        phi = centre + half + pad - x0
        p_lo = 0.0 if plo <= 0.0 else plo
        p_hi = top if phi >= top else phi
        has_centre = (plo != plo) | (phi != phi) | (math.ceil(p_lo) <= math.floor(p_hi))
        keep[r] = (r >= r_lo) & (r <= r_hi) & (not (disc < 0.0)) & has_centre


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
        verdict, mx, my, A, B, C, det, q, r_lo, r_hi = _slot_screen(tab, s, x0, x1, y0, y1, eps,
                                                                   screen)
        if verdict == _SKIP:
            continue
        if verdict == _ALL_ROWS:
            for r in range(T):
                k = cnt[r]
                rs[r, k] = s
                lo[r, k] = 0
                hi[r, k] = T - 1
                cnt[r] = k + 1
            continue
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


@njit(cache=True, error_model="numpy")
def _row_lists(tab, L, xs, ys, eps, screen, cnt, rs, keep):
    """Per pixel row r: the slots whose screen chord (:func:`_chords`, same arithmetic, same
    decisions) contains a pixel centre of row r, in list order (rs[r, :cnt[r]]).  The columns are
    not kept: the compositing lanes test alpha >= 1/255 themselves, and outside its chord a
    fragment fails that test (module docstring, Screen), so only the rows matter.  The chord test
    runs for all 16 rows at once (vectorised) into the scratch ``keep`` (16,) bool."""
    T = TILE_SIZE
    cnt[:] = 0
    x0 = np.float64(xs[0])
    x1 = np.float64(xs[T - 1])
    y0 = np.float64(ys[0])
    y1 = np.float64(ys[T - 1])
    for s in range(L):
        verdict, mx, my, A, B, C, det, q, r_lo, r_hi = _slot_screen(tab, s, x0, x1, y0, y1, eps,
                                                                   screen)
        if verdict == _SKIP:
            continue
        if verdict == _ALL_ROWS:
            for r in range(T):
                rs[r, cnt[r]] = s
                cnt[r] += 1
            continue
        _rows_keep(mx, my, A, B, C, det, q, x0, ys, r_lo, r_hi, keep)
        for r in range(r_lo, r_hi + 1):
            if keep[r]:
                rs[r, cnt[r]] = s
                cnt[r] += 1


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
def composite_forward(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg, rc,
                      eps, stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib,
                      last_img, final_T, row_cnt, row_slots):
    """Front-to-back compositing (RAS-03..RAS-06) of the pixels of tiles [lo, hi).

    gauss/offsets/pos from :func:`build_tile_lists`; per-Gaussian means2d (N,2) (in D, or float64
    for float32 compositing of float64 geometry: :func:`_gather`), conics (N,3),
    opac (N,), colors (N,3), depths (N,); bg (3,), rc the R_* constants, eps the dtype's machine
    epsilon (float64); outputs image (H,W,3), alpha_img / depth_img / final_T (H,W) in D,
    n_contrib (H,W) int32 (1-based position in the full tile list, RAS-06, through ``pos``) and
    last_img (H,W) int32 (the same in the live list, for the backward), written for these tiles
    only.  The screen's row lists are kept for the
    backward: row_cnt (n_tiles, 16) int64 and, for tile t with list length L, row_slots (16 P,)
    int32 holds its (16, L) table at [16 offsets[t], 16 offsets[t+1]).
    """
    H, W = alpha_img.shape
    one, zero, t_min = rc[R_ONE], rc[R_ZERO], rc[R_T_MIN]
    neg_half, cap, amin = rc[R_NEG_HALF], rc[R_CAP], rc[R_ALPHA_MIN]
    dt = conics.dtype                       # the compositing dtype (means2d may be float64)
    Lm = _max_len(offsets, lo, hi)
    tab = np.empty((Lm, N_TAB), dt)
    # per pixel of the row: T, colour r, g, b, depth, done (1 / 0) at lane offsets _S_* (one
    # array, fixed offsets, so that LLVM can vectorise the lane loop)
    st = np.empty(_N_STATE * TILE_SIZE, dt)
    last = np.empty(TILE_SIZE, np.int32)
    keep = np.empty(TILE_SIZE, np.bool_)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = _centres(tx * TILE_SIZE, tab)
        ys = _centres(ty * TILE_SIZE, tab)
        cnt, rs = _row_tables(tile, start, L, row_cnt, row_slots)
        _row_lists(tab, L, xs, ys, eps, screen, cnt, rs, keep)
        ncols = min(TILE_SIZE, W - tx * TILE_SIZE)
        for r in range(TILE_SIZE):
            i = ty * TILE_SIZE + r
            if i >= H:
                break
            py = ys[r]
            for c in range(TILE_SIZE):
                st[_S_T + c] = one
                st[_S_R + c] = zero
                st[_S_G + c] = zero
                st[_S_B + c] = zero
                st[_S_Z + c] = zero
                st[_S_DONE + c] = one if c >= ncols else zero   # columns past the image edge
                last[c] = 0
            n_done = TILE_SIZE - ncols
            for k in range(cnt[r]):
                s = rs[r, k]
                mx, A, B, o, lx = tab[s, 0], tab[s, 2], tab[s, 3], tab[s, 5], tab[s, 10]
                dy = (tab[s, 1] - py) + tab[s, 11]
                Cdy2 = tab[s, 4] * dy * dy
                cr, cg, cb, z = tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                slot = np.int32(s + 1)
                stops = 0
                # all 16 lanes at once, masked (vectorised); a lane does what the per-pixel loop
                # of the spec does: skip when done, power > 0 (RAS-03) or alpha < 1/255
                # (RAS-04); stop without blending (RAS-05); else blend
                for c in range(TILE_SIZE):
                    power = _power(A, B, Cdy2, (mx - xs[c]) + lx, dy, neg_half)
                    a = min(cap, o * fast_exp(power))
                    Tc = st[_S_T + c]
                    test_T = Tc * (one - a)
                    live = ((st[_S_DONE + c] == zero) & (not (power > zero))
                            & (not (a < amin)))
                    stop = live & ((test_T <= t_min) if stop_inclusive else (test_T < t_min))
                    blend = live & (not stop)
                    stops += stop
                    w = a * Tc
                    st[_S_DONE + c] = one if stop else st[_S_DONE + c]
                    st[_S_R + c] = st[_S_R + c] + cr * w if blend else st[_S_R + c]
                    st[_S_G + c] = st[_S_G + c] + cg * w if blend else st[_S_G + c]
                    st[_S_B + c] = st[_S_B + c] + cb * w if blend else st[_S_B + c]
                    st[_S_Z + c] = st[_S_Z + c] + z * w if blend else st[_S_Z + c]
                    st[_S_T + c] = test_T if blend else Tc
                    last[c] = slot if blend else last[c]
                n_done += stops
                if n_done == TILE_SIZE:
                    break
            for c in range(ncols):
                j = tx * TILE_SIZE + c
                Tc = st[_S_T + c]
                image[i, j, 0] = st[_S_R + c] + Tc * bg[0]
                image[i, j, 1] = st[_S_G + c] + Tc * bg[1]
                image[i, j, 2] = st[_S_B + c] + Tc * bg[2]
                alpha_img[i, j] = one - Tc
                depth_img[i, j] = st[_S_Z + c]
                lc = last[c]
                last_img[i, j] = lc
                n_contrib[i, j] = pos[start + lc - 1] + 1 if lc > 0 else 0
                final_T[i, j] = Tc


@njit(cache=True, nogil=True, error_model="numpy")
def composite_backward(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                       grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth,
                       row_cnt, row_slots, contrib):
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
    saturated pixel, typically far less because the roundings do not all add up).  The row lists are the
    forward's (row_cnt, row_slots), last_img its live-list n_contrib.
    Writes contrib (P, 10): row offsets[t] + s = the sum over tile t's pixels for list slot s
    (in the fixed lane-pair order of the module docstring), columns G_* (means2d x, y; conic A, B,
    C; opacity; colour r, g, b; depth).
    """
    H, W = final_T.shape
    one, zero, neg_half, cap = rc[R_ONE], rc[R_ZERO], rc[R_NEG_HALF], rc[R_CAP]
    amin = rc[R_ALPHA_MIN]
    dt = conics.dtype                       # the compositing dtype (means2d may be float64)
    Lm = _max_len(offsets, lo, hi)
    tab = np.empty((Lm, N_TAB), dt)
    # per list slot, gradient field and lane pair (c, c + 8): partial sums over the tile's rows,
    # reduced over the 8 lane pairs in a fixed order when the tile is done
    acc = np.empty(Lm * _NT_HALF, dt)
    # per pixel of the row (lane offsets _B_*): T, suffix sum, tail, v_image r, g, b, v_depth
    st = np.empty(_N_BSTATE * TILE_SIZE, dt)
    last = np.empty(TILE_SIZE, np.int32)
    # one list slot's per-lane gradient terms, field-major (G_* x 16)
    terms = np.empty(N_GRAD_COLUMNS * TILE_SIZE, dt)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        _gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = _centres(tx * TILE_SIZE, tab)
        ys = _centres(ty * TILE_SIZE, tab)
        cnt, rs = _row_tables(tile, start, L, row_cnt, row_slots)
        acc[:L * _NT_HALF] = zero
        ncols = min(TILE_SIZE, W - tx * TILE_SIZE)
        for r in range(TILE_SIZE):
            i = ty * TILE_SIZE + r
            if i >= H:
                break
            py = ys[r]
            max_last = 0
            for c in range(TILE_SIZE):
                if c < ncols:
                    j = tx * TILE_SIZE + c
                    last[c] = last_img[i, j]
                    max_last = max(max_last, last[c])
                    Tf = final_T[i, j]
                    vr, vg, vb, vz = v_image[i, j, 0], v_image[i, j, 1], v_image[i, j, 2], v_depth[i, j]
                    va = v_alpha[i, j]
                else:                                    # past the image edge: no fragments
                    last[c] = 0
                    Tf = vr = vg = vb = vz = va = zero
                st[_B_T + c] = Tf
                st[_B_SUF + c] = zero
                st[_B_VR + c], st[_B_VG + c], st[_B_VB + c], st[_B_VZ + c] = vr, vg, vb, vz
                st[_B_TAIL + c] = Tf * (vr * bg[0] + vg * bg[1] + vb * bg[2] - va)
            for k in range(cnt[r] - 1, -1, -1):           # back to front
                s = rs[r, k]
                if s >= max_last:
                    continue
                mx, A, B, C, o = tab[s, 0], tab[s, 2], tab[s, 3], tab[s, 4], tab[s, 5]
                lx = tab[s, 10]
                dy = (tab[s, 1] - py) + tab[s, 11]
                Cdy2 = C * dy * dy
                cr, cg, cb, z = tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                s32 = np.int32(s)
                # all 16 lanes at once, masked (vectorised); a lane is one pixel's step of the
                # back-to-front walk: only fragments the forward blended (s < last, power <= 0,
                # alpha >= 1/255) change T and the suffix sum or contribute
                for c in range(TILE_SIZE):
                    dx = (mx - xs[c]) + lx
                    power = _power(A, B, Cdy2, dx, dy, neg_half)
                    G = fast_exp(power)
                    oG = o * G
                    a = min(cap, oG)
                    live = (s32 < last[c]) & (not (power > zero)) & (not (a < amin))
                    inv = one / (one - a)
                    Ti = st[_B_T + c] * inv                  # T before this fragment
                    vr, vg, vb, vz = st[_B_VR + c], st[_B_VG + c], st[_B_VB + c], st[_B_VZ + c]
                    cv = cr * vr + cg * vg + cb * vb + z * vz
                    w = a * Ti
                    suf = st[_B_SUF + c]
                    v_a = Ti * cv - (suf + st[_B_TAIL + c]) * inv
                    st[_B_T + c] = Ti if live else st[_B_T + c]
                    st[_B_SUF + c] = suf + w * cv if live else suf
                    v_oG = v_a if (live & (grad_through_cap | (oG <= cap))) else zero   # RAS-10
                    v_pow = v_oG * o * G
                    wl = w if live else zero
                    g_mx = -(A * dx + B * dy) * v_pow
                    g_my = -(C * dy + B * dx) * v_pow
                    g_a = neg_half * dx * dx * v_pow
                    g_b = -dx * dy * v_pow                                        # RAS-08
                    g_c = neg_half * dy * dy * v_pow
                    # selects, not products with 0: a huge conic outside the chord could give inf * 0
                    terms[G_MX * TILE_SIZE + c] = g_mx if live else zero
                    terms[G_MY * TILE_SIZE + c] = g_my if live else zero
                    terms[G_A * TILE_SIZE + c] = g_a if live else zero
                    terms[G_B * TILE_SIZE + c] = g_b if live else zero
                    terms[G_C * TILE_SIZE + c] = g_c if live else zero
                    terms[G_O * TILE_SIZE + c] = v_oG * G
                    terms[G_R * TILE_SIZE + c] = wl * vr
                    terms[G_G * TILE_SIZE + c] = wl * vg
                    terms[G_BL * TILE_SIZE + c] = wl * vb
                    terms[G_Z * TILE_SIZE + c] = wl * vz
                base = s * _NT_HALF
                for f in range(N_GRAD_COLUMNS):
                    for c in range(_HALF):
                        acc[base + f * _HALF + c] += terms[f * TILE_SIZE + c] + terms[f * TILE_SIZE + c + _HALF]
        for s in range(L):                       # the lane pairs in a fixed order, 0..7
            base = s * _NT_HALF
            for f in range(N_GRAD_COLUMNS):
                total = zero
                for c in range(_HALF):
                    total += acc[base + f * _HALF + c]
                contrib[start + s, f] = total


@njit(cache=True, nogil=True, error_model="numpy")
def reduce_by_gaussian(lo, hi, gauss, contrib, out):
    """out[g] += contrib[p] for every intersection p of a Gaussian g = gauss[p] with
    lo <= g < hi, in intersection order (a fixed-order, race-free reduction: each Gaussian's sum
    has the same order whatever the split of [0, N) into ranges).  out (N, 10) zero-initialised."""
    for p in range(gauss.size):
        g = gauss[p]
        if lo <= g < hi:
            for k in range(contrib.shape[1]):
                out[g, k] += contrib[p, k]
