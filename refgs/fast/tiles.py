"""A tile's table, the screen, live intersections and the tile lists (numba kernels).

Same model as refgs.rasterize (RAS-01, RAS-02, RAS-09); used by the compositing kernels of
refgs.fast.kernels and by refgs.fast.ties.

* :func:`build_tile_lists` -- every tile's list of covering Gaussians sorted by depth, ties by
  Gaussian index (RAS-01, RAS-02): the visible Gaussians are sorted once (a stable argsort by
  depth, done by the caller) and dealt to the tiles of their rectangles in that order (a counting
  sort), so each list comes out sorted.  O(N + P) for P intersections.  Only *live*
  intersections are dealt (:func:`tile_alive`: tiles where the screen below can keep the
  Gaussian in some pixel row; on trained fern models 1/4 of the 3-sigma rectangles' tiles),
  each with its position in the full list (``pos``), so n_contrib still counts the spec's lists.
* :func:`gather` -- a tile's list as a contiguous per-slot table (mean, conic, opacity, colour,
  depth, the mean's residual), what the compositing and the screen read.

Screen (RAS-09: an implementation device, not part of the model).  Per tile, for each list slot
and each of the 16 pixel rows, the columns where alpha could reach 1/255 are the chord of the
ellipse d^T conic d <= q' with q' = 2 ln(255 o) widened by a bound on the rounding error of the
computed power (SCREEN_ULPS eps |terms|) plus SCREEN_MARGIN; the chord is solved in float64 and
padded for its own rounding.  A fragment outside its chord has computed o G < 1/255 by at least a
factor exp(-SCREEN_MARGIN / 2), so skipping it changes nothing; fragments inside are evaluated
exactly as the spec says.  Non-positive-definite conics and non-finite values get no screen. The
compositing kernels take, per slot, the half rows (8 pixels) where the row's chord holds a pixel
centre (:func:`slot_rows`, a 32-bit mask; :func:`screen_slots` gives it for all of a tile's
slots at once, across the slots) and evaluate all lanes of those halves (the lanes
outside the chord fail the alpha test by the bound above; :func:`chords` keeps the columns too,
for refgs.fast.ties).  Before any tile is composited, :func:`tile_alive` applies the same bound
per Gaussian and tile of its rectangle, conservatively (q at its largest over the rectangle, every
bound widened), so a tile list leaves out only Gaussians the screen would skip in every row of
that tile: no output changes, and the compositing no longer gathers and screens them
(tests/test_fast.py::test_live_intersections_contain_every_slot_the_screen_keeps).
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
#: the column where a tile row's second half starts (the screen's half-row masks, :func:`slot_rows`)
_HALF_COL = float(TILE_SIZE // 2)
#: columns of a tile's per-slot table (:func:`gather`)
N_TAB = 12


#: bits per pass of :func:`radix_argsort` (a 2^16-entry count table, 512 KB: in L2)
RADIX_BITS = 16


@njit(cache=True, nogil=True, error_model="numpy")
def radix_argsort(keys, nbits):
    """The stable argsort of ``keys`` (n,) int64 by their low ``nbits`` bits read as an unsigned
    number: a least-significant-digit radix sort, RADIX_BITS per pass (a pass whose digit is the
    same for every key is skipped); stable, so equal keys keep their order.  O(n) per pass."""
    n = keys.size
    mask = (1 << RADIX_BITS) - 1
    idx = np.arange(n)
    k = keys.copy()
    idx2 = np.empty(n, np.int64)
    k2 = np.empty(n, np.int64)
    count = np.empty(mask + 2, np.int64)
    for shift in range(0, nbits, RADIX_BITS):
        count[:] = 0
        for i in range(n):
            count[((k[i] >> shift) & mask) + 1] += 1
        if count.max() == n:
            continue                                   # one digit for all keys: order unchanged
        for d in range(mask + 1):
            count[d + 1] += count[d]
        for i in range(n):
            d = (k[i] >> shift) & mask
            j = count[d]
            count[d] = j + 1
            k2[j] = k[i]
            idx2[j] = idx[i]
        k, k2 = k2, k
        idx, idx2 = idx2, idx
    return idx


@njit(cache=True, nogil=True, error_model="numpy")
def rects_in_order(order, rect):
    """rect[order] (V, 4) int64: the tile rectangles of the visible Gaussians in depth order, so
    that the passes of :func:`build_tile_lists` read them front to back, not scattered."""
    out = np.empty((order.size, 4), np.int64)
    for k in range(order.size):
        g = order[k]
        for j in range(4):
            out[k, j] = rect[g, j]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def tile_counts(lo, hi, chunk, rect_s, rect_off, live, gx, counts, full):
    """The first pass of :func:`build_tile_lists` for the Gaussians order[lo:hi], into row
    c = lo // chunk of counts and full (C, n_tiles) int64: counts[c, t] += how many of them are
    live in tile t (``live``, :func:`tile_alive`), full[c, t] += how many hold t in their
    rectangle.  rect_s: :func:`rects_in_order`."""
    c = lo // chunk
    for k in range(lo, hi):
        x0, x1, y0, y1 = rect_s[k, 0], rect_s[k, 1], rect_s[k, 2], rect_s[k, 3]
        i = rect_off[k]
        for ty in range(y0, y1):
            row = ty * gx
            for tx in range(x0, x1):
                counts[c, row + tx] += live[i]
                full[c, row + tx] += 1
                i += 1


@njit(cache=True, nogil=True, error_model="numpy")
def tile_fill(lo, hi, chunk, order, rect_s, rect_off, live, gx, cursor, full, gauss, pos):
    """The second pass for the Gaussians order[lo:hi], in that order, with row c = lo // chunk
    of cursor and full (C, n_tiles): each Gaussian appended to the lists of the tiles where it is
    live (cursor[c, t]: this chunk's next free position in tile t's list) with pos = its position
    in the tile's full list (every Gaussian whose rectangle holds the tile, live or not; full[c, t]
    starts at the number of those in the chunks before), which is what n_contrib reports
    (RAS-06)."""
    c = lo // chunk
    for k in range(lo, hi):
        g = order[k]
        x0, x1, y0, y1 = rect_s[k, 0], rect_s[k, 1], rect_s[k, 2], rect_s[k, 3]
        i = rect_off[k]
        for ty in range(y0, y1):
            row = ty * gx
            for tx in range(x0, x1):
                t = row + tx
                if live[i]:
                    j = cursor[c, t]
                    gauss[j] = g
                    pos[j] = full[c, t]
                    cursor[c, t] = j + 1
                full[c, t] += 1
                i += 1


def chunk_starts(counts, full, offsets):
    """(cursor, full_start) (C, n_tiles) for :func:`tile_fill` from the first pass' per-chunk
    counts: chunk c's lists start after every earlier chunk's entries of the same tile."""
    cursor = offsets[:-1] + (np.cumsum(counts, axis=0) - counts)
    return cursor, np.cumsum(full, axis=0) - full


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
def screen_inputs(lo, hi, order, means2d, conics, opac, out):
    """out[k] = (mx, my, A, B, C, o) of Gaussian order[k] in float64, k = lo..hi: what
    :func:`tile_alive` reads, gathered in depth order by a loop that does nothing else (its
    cache misses overlap, where inside tile_alive's arithmetic they stall it)."""
    for k in range(lo, hi):
        g = order[k]
        out[k, 0] = np.float64(means2d[g, 0])
        out[k, 1] = np.float64(means2d[g, 1])
        out[k, 2] = np.float64(conics[g, 0])
        out[k, 3] = np.float64(conics[g, 1])
        out[k, 4] = np.float64(conics[g, 2])
        out[k, 5] = np.float64(opac[g])


@njit(cache=True, nogil=True, error_model="numpy")
def tile_alive(lo, hi, rect_s, rect_off, scr, eps, live):
    """For the Gaussians k = lo..hi of the depth order: live[rect_off[k] + (ty - y0) (x1 - x0) +
    (tx - x0)] for each tile (tx, ty) of their rectangle rect_s[k] (:func:`rects_in_order`);
    scr (V, 6) float64: their mean, conic and opacity in that order (:func:`screen_inputs`), so
    that this loop, long per Gaussian, reads its inputs in sequence (docs/fast.md, "Speed").

    Conservative: a tile is live unless no pixel centre of it can lie inside the screen's
    ellipse d^T conic d <= q (module docstring, Screen), with q taken at its largest over the
    rectangle (the rounding term grows with the distance to the mean) and every bound widened by
    _LIVE_REL / _LIVE_PAD; so every slot that :func:`slot_rows` keeps in some row is live, and a
    slot that is not live has o G < 1/255 at every pixel centre of the tile: leaving it out of
    the tile's list changes no output (the forward's screen then drops the live slots it does not
    keep, as before).  Per tile row, the ellipse's x-range over the row's pixel-centre band is the
    range of the chord ends mx + (B/A) dy +- sqrt(A q - det dy^2) / A, at their extremes
    dy = +-B sqrt(q / (det C)) clamped to the band (d = mean - pixel, dy = my - py).  Odd or
    non-finite conics are live everywhere (the screen's _ALL_ROWS)."""
    T = TILE_SIZE
    for k in range(lo, hi):
        rx0, rx1, ry0, ry1 = rect_s[k, 0], rect_s[k, 1], rect_s[k, 2], rect_s[k, 3]
        base = rect_off[k]
        w = rx1 - rx0
        mx, my, A, B, C, o = scr[k, 0], scr[k, 1], scr[k, 2], scr[k, 3], scr[k, 4], scr[k, 5]
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


def build_tile_lists(order, rect, n_tiles, gx, rect_off, live):
    """Per-tile Gaussian lists in depth order (RAS-01, RAS-02), of the live intersections.

    order (V,) int64: visible Gaussians sorted by (depth, index); rect (N,4) int64 (x0,x1,y0,y1),
    max exclusive; rect_off (V+1,) int64: start of order[k]'s rectangle in ``live`` (row-major),
    live (rect_off[V],) bool (all True: the full lists of the spec).  Returns (gauss (P,) int64,
    offsets (n_tiles+1,) int64, pos (P,) int32): tile t's list is gauss[offsets[t]:offsets[t+1]],
    pos the positions in the full lists.  (refgs.fast.render runs both passes over chunks of the
    Gaussians in parallel, with the same result: a chunk's entries of a tile go after those of
    the chunks before, :func:`chunk_starts`.)
    """
    V = order.size
    rect_s = rects_in_order(order, rect)
    counts, full = np.zeros((1, n_tiles), np.int64), np.zeros((1, n_tiles), np.int64)
    tile_counts(0, V, max(V, 1), rect_s, rect_off, live, gx, counts, full)
    offsets = np.zeros(n_tiles + 1, np.int64)
    np.cumsum(counts[0], out=offsets[1:])
    cursor, full_start = chunk_starts(counts, full, offsets)
    gauss = np.empty(int(offsets[n_tiles]), np.int64)
    pos = np.empty(int(offsets[n_tiles]), np.int32)
    tile_fill(0, V, max(V, 1), order, rect_s, rect_off, live, gx, cursor, full_start, gauss, pos)
    return gauss, offsets, pos


@njit(cache=True, error_model="numpy")
def gather(gauss, start, L, means2d, conics, opac, colors, depths, tab):
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
def max_len(offsets, lo, hi):
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
    :func:`_log_term` of o): (verdict, det, q, r_lo, r_hi), all float64; verdict _SKIP (o G <
    1/255 in the whole tile), _ALL_ROWS (no screen: switched off, odd conic or non-finite bound)
    or _SCREENED (rows r_lo..r_hi, whole numbers, may hold a chord; r_lo, r_hi mean nothing for
    the other verdicts).  Straight-line code, every choice a select, so that :func:`screen_slots`
    runs it in SIMD lanes across a tile's slots; :func:`chords` and :func:`slot_rows` call it
    per slot (:func:`_slot_screen`)."""
    top = TILE_SIZE - 1.0
    det = A * C - B * B
    ax0, ax1 = abs(mx - x0), abs(mx - x1)
    ay0, ay1 = abs(my - y0), abs(my - y1)
    dxm = ax1 if ax1 > ax0 else ax0
    dym = ay1 if ay1 > ay0 else ay0
    terms = abs(A) * dxm * dxm + abs(C) * dym * dym + 2.0 * abs(B) * dxm * dym
    q = lg + SCREEN_ULPS * eps * terms + SCREEN_MARGIN
    finite = (det - det == 0.0) & (q - q == 0.0) & (mx - mx == 0.0) & (my - my == 0.0)
    odd = (not screen) | (not ((A > 0.0) & (C > 0.0) & (det > 0.0) & finite))
    # rows where the chord can be non-empty: dy^2 (det - F (AC + B^2)) <= A q (1 + F)
    den = det - _F64_ULPS * (A * C + B * B)
    band = den > 0.0
    dy_max = math.sqrt(A * q * (1.0 + _F64_ULPS) / den) * (1.0 + _F64_ULPS) + _CHORD_PAD
    ylo = my - dy_max - y0
    yhi = my + dy_max - y0
    empty = (not (q > 0.0)) | (band & ((yhi < 0.0) | (ylo > top)))   # o G < 1/255 everywhere
    verdict = _SKIP if (screen & (o == 0.0)) else (                  # alpha = 0 everywhere
        _ALL_ROWS if odd else (_SKIP if empty else _SCREENED))
    r_lo = math.ceil(ylo) if (band & (ylo > 0.0)) else 0.0
    r_hi = math.floor(yhi) if (band & (yhi < top)) else top
    return np.float64(verdict), det, q, np.float64(r_lo), np.float64(r_hi)


@njit(cache=True, inline="always", error_model="numpy")
def _slot_screen(tab, s, x0, x1, y0, y1, eps, screen):
    """:func:`_screen_values` of list slot s of a tile's table: (verdict, mx, my, A, B, C, det, q,
    r_lo, r_hi) in float64, r_lo and r_hi as ints (0, -1 unless _SCREENED)."""
    mx = np.float64(tab[s, 0]) + np.float64(tab[s, 10])     # the mean the lanes see
    my = np.float64(tab[s, 1]) + np.float64(tab[s, 11])
    A, B, C = np.float64(tab[s, 2]), np.float64(tab[s, 3]), np.float64(tab[s, 4])
    o = np.float64(tab[s, 5])
    verdict, det, q, r_lo, r_hi = _screen_values(mx, my, A, B, C, o, _log_term(o), x0, x1, y0, y1,
                                                 eps, screen)
    if verdict != _SCREENED:
        return verdict, mx, my, A, B, C, det, q, 0, -1
    return verdict, mx, my, A, B, C, det, q, int(r_lo), int(r_hi)


@njit(cache=True, inline="always", error_model="numpy")
def _rows_keep(mx, my, A, B, C, det, q, x0, ys, r_lo, r_hi):
    """Which half rows hold a pixel centre of the screen's chord, for a _SCREENED slot: bit 2 r
    for columns x0 .. x0 + 7 of row r (pixel centre ys[r]), bit 2 r + 1 for x0 + 8 .. x0 + 15;
    rows outside r_lo..r_hi have none.  All 16 rows at once (vectorised: float rounding, no
    branches, the bits or-ed together); :func:`slot_rows`' test (the same arithmetic as
    :func:`chords`, so both take the same decisions)."""
    T = TILE_SIZE
    top = T - 1.0
    inv_a = 1.0 / A
    b_a = B * inv_a
    a_q = A * q
    ac_b2 = A * C + B * B
    mask = 0
    for r in range(T):
        dy = my - np.float64(ys[r])
        dy2 = dy * dy
        disc = a_q - det * dy2 + _F64_ULPS * (a_q + ac_b2 * dy2)
        half = math.sqrt(0.0 if disc < 0.0 else disc) * inv_a
        centre = mx + b_a * dy
        pad = _F64_ULPS * (abs(b_a * dy) + half + abs(mx)) + _CHORD_PAD
        plo = centre - half - pad - x0
        phi = centre + half + pad - x0
        c_lo = np.ceil(0.0 if plo <= 0.0 else plo)       # first and last pixel column inside
        c_hi = np.floor(top if phi >= top else phi)
        nan = (plo != plo) | (phi != phi)
        row = (r >= r_lo) & (r <= r_hi) & (not (disc < 0.0))
        left = row & (nan | (c_lo <= min(c_hi, _HALF_COL - 1.0)))
        right = row & (nan | (max(c_lo, _HALF_COL) <= c_hi))
        mask |= (np.int64(left) | (np.int64(right) << 1)) << (2 * r)
    return mask


@njit(cache=True, error_model="numpy")
def chords(tab, L, xs, ys, eps, screen, cnt, rs, lo, hi):
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
def slot_rows(tab, s, x0, x1, y0, y1, ys, eps, screen):
    """Where the screen keeps list slot s in the tile (module docstring, Screen), as a bit mask
    of half rows: bit 2 r for columns 0..7 of pixel row r, bit 2 r + 1 for columns 8..15 (int64).
    0 when o G < 1/255 in the whole tile; every bit without a screen (``screen`` False, odd
    conics, non-finite bounds); else the halves that hold a pixel centre of the row's chord (the
    columns of :func:`chords`).  x0, x1, y0, y1: the tile's first and last pixel centres
    (float64); ys (16,) the row centres.  The readable one-slot form: the compositing calls
    :func:`screen_slots`, the same masks for a whole tile (tests/test_fast.py compares them)."""
    T = TILE_SIZE
    verdict, mx, my, A, B, C, det, q, r_lo, r_hi = _slot_screen(tab, s, x0, x1, y0, y1, eps,
                                                               screen)
    if verdict == _SKIP:
        return np.int64(0)
    if verdict == _ALL_ROWS:
        return np.int64((1 << (2 * T)) - 1)
    return _rows_keep(mx, my, A, B, C, det, q, x0, ys, r_lo, r_hi)


#: rows of :func:`screen_slots`' scratch (float64, one column per list slot)
_SC_LG, _SC_MX, _SC_MY, _SC_DET, _SC_Q, _SC_RLO, _SC_RHI, _SC_VERDICT = range(8)
N_SCREEN_ROWS = 8


@njit(cache=True, error_model="numpy")
def screen_slots(tab, L, x0, x1, y0, y1, ys, eps, screen, scr, out):
    """out[s] = :func:`slot_rows` (tab, s, ...) for every list slot s < L of a tile, bit for bit
    (tests/test_fast.py checks it), computed across the slots: the per-slot part of the screen
    (:func:`_screen_values`, straight-line code) runs as lanes of 8 slots (float64 SIMD), and
    only the row masks (:func:`_rows_keep`, itself vectorised over
    the 16 rows) run slot by slot.  scr (N_SCREEN_ROWS, >= L) float64 is caller-owned scratch.
    The log of the opacity term is a library call, so it has a loop of its own."""
    T = TILE_SIZE
    for s in range(L):
        scr[_SC_LG, s] = _log_term(np.float64(tab[s, 5]))
    for s in range(L):              # lanes: _screen_values is one basic block
        mx = np.float64(tab[s, 0]) + np.float64(tab[s, 10])
        my = np.float64(tab[s, 1]) + np.float64(tab[s, 11])
        verdict, det, q, r_lo, r_hi = _screen_values(
            mx, my, np.float64(tab[s, 2]), np.float64(tab[s, 3]), np.float64(tab[s, 4]),
            np.float64(tab[s, 5]), scr[_SC_LG, s], x0, x1, y0, y1, eps, screen)
        scr[_SC_MX, s] = mx
        scr[_SC_MY, s] = my
        scr[_SC_DET, s] = det
        scr[_SC_Q, s] = q
        scr[_SC_RLO, s] = r_lo
        scr[_SC_RHI, s] = r_hi
        scr[_SC_VERDICT, s] = verdict
    for s in range(L):
        verdict = scr[_SC_VERDICT, s]
        if verdict == _SKIP:
            out[s] = 0
        elif verdict == _ALL_ROWS:
            out[s] = (1 << (2 * T)) - 1
        else:
            out[s] = _rows_keep(scr[_SC_MX, s], scr[_SC_MY, s], np.float64(tab[s, 2]),
                                np.float64(tab[s, 3]), np.float64(tab[s, 4]), scr[_SC_DET, s],
                                scr[_SC_Q, s], x0, ys, int(scr[_SC_RLO, s]), int(scr[_SC_RHI, s]))


@njit(cache=True, inline="always", error_model="numpy")
def gaussian_power(A, B, Cdy2, dx, dy, neg_half):
    """-0.5 (A dx^2 + C dy^2) - B dx dy with d = mean - pixel (RAS-03), C dy^2 precomputed per row
    (the same operations, in the same order, as refgs.rasterize)."""
    return neg_half * (A * dx * dx + Cdy2) - B * dx * dy


@njit(cache=True, error_model="numpy")
def centres(origin, like):
    """Pixel centres origin + k + 0.5, k = 0..15 (CNV-08), in the dtype of ``like``."""
    c = np.empty(TILE_SIZE, like.dtype)
    for k in range(TILE_SIZE):
        c[k] = origin + k + 0.5
    return c
