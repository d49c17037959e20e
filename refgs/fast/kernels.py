"""Per-pixel front-to-back compositing, forward and backward, as numba kernels.

Same model as refgs.rasterize (RAS-03..RAS-10, PRF-05..PRF-07); the loop is the literal per-pixel
loop of the spec instead of the reference's batched cumprod.  The tile lists, the per-slot table
and the screen are refgs.fast.tiles'.

* :func:`composite_forward` -- over a range of tiles; every pixel sees its tile's list front to
  back: power (skip > 0), alpha = min(cap, o G) (skip < 1/255), the profile's stop rule on
  T (1 - alpha) with the saturating Gaussian not blended, colour / depth accumulation, T_final and
  n_contrib (1-based list position of the last blended Gaussian).  The list slot is the outer
  loop: each slot is screened once (refgs.fast.tiles.slot_rows, the rows its chord reaches;
  all of a tile's slots before the slot loop, refgs.fast.tiles.screen_slots), then visits those
  rows of the tile, and in each row its 16 pixels; every pixel keeps its own
  T, colour, depth and done flag, so each pixel sees the slots in list order, which is the
  per-pixel front-to-back order of the spec.  The row's 16 pixels are 16 *lanes* computed
  without branches (every test a mask; every update an unconditional store of arithmetic that
  leaves the value as it is where the lane does not blend: + 0, * 1), so LLVM turns the lane
  loop into SIMD code; exp is refgs.fast.fexp.fast_exp (within 1 ulp of exp; ``math.exp`` is a
  scalar library call that stops vectorisation).  The per-pixel state, the pixel centres' x and
  the last blended slot (counted in the dtype, exact up to MAX_LIST_LENGTH) live in one array at
  fixed offsets, so the lane loop needs no run-time alias checks.  A row is left once its 16
  pixels have stopped, the tile once every row has.
* :func:`composite_backward` -- over a range of tiles; each pixel's blended fragments are walked
  back to front from list position n_contrib (the tile starts at its largest), T_i recovered from
  T_final by division as the original does (T_i = T_{i+1} * (1 / (1 - alpha_i)); docs/fast.md,
  "T recovery"), and the suffix sum of RAS-07 (16 masked lanes, as in the forward), slot by
  slot over the rows the forward's screen kept (``row_mask``).  Each slot's contributions are
  summed over the tile in a fixed order -- per lane over the rows top to bottom (in the lane
  loop, SIMD), then the 16 lane sums in lane order -- into a buffer row per intersection;
  :func:`reduce_by_gaussian` then adds the rows into per-Gaussian gradients in intersection
  order (threads split the Gaussians, not the intersections).  No atomics, no races: the result
  is bit-identical for any thread count and any split of the tiles into work items.

Multiply-adds.  Each kernel exists twice, with one body: ``composite_forward`` /
``composite_backward`` evaluate every expression in the reference's operation order, one
rounding per operation (float64: results within ~1e-15 of refgs.rasterize); the ``_fma`` variants
let LLVM fuse a multiply and an add into one FMA (numba ``fastmath={"contract"}``, nothing
else), one rounding instead of two, as GPU compilers do by default -- 8-18 % faster
(docs/fast.md, "Speed").  refgs.fast.render uses the ``_fma`` variants for float32 compositing,
the exact ones for float64 (COMPOSITING_KERNELS).
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from ..constants import TILE_SIZE
from .fexp import fast_exp
from .tiles import N_SCREEN_ROWS, N_TAB, centres, gather, gaussian_power, max_len, screen_slots

# indices of the compositing constants array (in the Gaussians' dtype)
R_ZERO, R_ONE, R_NEG_HALF, R_CAP, R_ALPHA_MIN, R_T_MIN = 0, 1, 2, 3, 4, 5
N_RASTER_CONSTANTS = 6
#: columns of the per-intersection / per-Gaussian gradient buffer
G_MX, G_MY, G_A, G_B, G_C, G_O, G_R, G_G, G_BL, G_Z = range(10)
N_GRAD_COLUMNS = 10
_NPIX = TILE_SIZE * TILE_SIZE
#: offsets of the forward's per-pixel state (T, colour r, g, b, depth, done flag, the pixel
#: centre's x, the last blended list slot as a number of the dtype), each a block of the tile's
#: 256 pixels (row-major) in one array: every access of the lane loop is then the same index
#: plus a constant, so LLVM proves them independent and needs no run-time alias checks
_S_T, _S_R, _S_G, _S_B, _S_Z, _S_DONE, _S_PX, _S_LAST = (k * _NPIX for k in range(8))
_N_STATE = 8
#: the backward's per-pixel state: T, suffix sum, tail, v_image r, g, b, v_depth, the pixel
#: centre's x, the last blended slot (as in the forward)
_B_T, _B_SUF, _B_TAIL, _B_VR, _B_VG, _B_VB, _B_VZ, _B_PX, _B_LAST = (k * _NPIX for k in range(9))
_N_BSTATE = 9
#: list slots are counted in the compositing dtype (the _S_LAST / _B_LAST blocks): exact up to
#: 2**24 in float32 (its 24-bit significand), 2**53 in float64; refgs.fast.render refuses longer
#: tile lists
MAX_LIST_LENGTH = {np.dtype(np.float32): 2 ** 24, np.dtype(np.float64): 2 ** 53}
#: lanes of half a tile row (the screen's half-row masks, refgs.fast.tiles.slot_rows)
_HALF = TILE_SIZE // 2


@njit(cache=True, inline="always", error_model="numpy")
def row_span(rows):
    """First and last pixel row with a bit in a non-zero half-row mask (refgs.fast.tiles.slot_rows:
    bits 2 r, 2 r + 1 for row r), from the mask's trailing and leading zero counts; masked to
    0..15 so that LLVM sees the row indices in range (no negative-index wrap in the lane loops)."""
    T = TILE_SIZE
    return (trailing_zeros(rows) >> 1) & (T - 1), ((63 - leading_zeros(rows)) >> 1) & (T - 1)


@njit(cache=True, inline="always", error_model="numpy")
def _forward_tiles(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg, rc, eps,
                   stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib, last_img,
                   final_T, row_mask):
    """The body of :func:`composite_forward` (inlined into both variants)."""
    H, W = alpha_img.shape
    T = TILE_SIZE
    one, zero, t_min = rc[R_ONE], rc[R_ZERO], rc[R_T_MIN]
    neg_half, cap, amin = rc[R_NEG_HALF], rc[R_CAP], rc[R_ALPHA_MIN]
    dt = conics.dtype                       # the compositing dtype (means2d may be float64)
    tab = np.empty((max_len(offsets, lo, hi), N_TAB), dt)
    scr = np.empty((N_SCREEN_ROWS, tab.shape[0]), np.float64)
    st = np.empty(_N_STATE * _NPIX, dt)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        gather(gauss, start, L, means2d, conics, opac, colors, depths, tab)
        xs = centres(tx * T, tab)
        ys = centres(ty * T, tab)
        ncols = min(T, W - tx * T)
        nrows = min(T, H - ty * T)
        for p in range(_NPIX):
            st[_S_T + p] = one
            st[_S_R + p] = zero
            st[_S_G + p] = zero
            st[_S_B + p] = zero
            st[_S_Z + p] = zero
            st[_S_LAST + p] = zero
            st[_S_PX + p] = xs[p & (T - 1)]
        live_rows = 0                            # rows with a pixel still compositing
        for r in range(T):
            for c in range(T):                   # pixels past the image edge are done
                st[_S_DONE + r * T + c] = one if (c >= ncols or r >= nrows) else zero
            if r < nrows and ncols > 0:
                live_rows |= 1 << r
        x0, x1 = np.float64(xs[0]), np.float64(xs[T - 1])
        y0, y1 = np.float64(ys[0]), np.float64(ys[T - 1])
        # the screen of every slot first, across the slots (tiles.screen_slots): the lanes'
        # branches then read a mask already computed, where a mask computed in the slot loop
        # resolves them late (its log, square roots and divisions) and stalls the pipeline on
        # every misprediction (docs/fast.md, "Speed")
        screen_slots(tab, L, x0, x1, y0, y1, ys, eps, screen, scr, row_mask[start:start + L])
        s = 0
        while s < L and live_rows != 0:
            rows = row_mask[start + s]
            if rows != 0:
                mx, my, A, B, C = tab[s, 0], tab[s, 1], tab[s, 2], tab[s, 3], tab[s, 4]
                o, cr, cg, cb, z = tab[s, 5], tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                lx, ly = tab[s, 10], tab[s, 11]
                slot = dt.type(s + 1)           # exact: L <= MAX_LIST_LENGTH
                r_first, r_last = row_span(rows)
                for r in range(r_first, r_last + 1):
                    halves = (rows >> (2 * r)) & 3
                    if halves == 0 or ((live_rows >> r) & 1) == 0:
                        continue
                    dy = (my - ys[r]) + ly
                    Cdy2 = C * dy * dy
                    b = r * T
                    stops = False                # a flag, not an int64 count: the widest type
                    #                              in the loop sets the lanes per vector
                    # the row's lanes at once (one or both halves), masked (vectorised); a lane
                    # does what the per-pixel loop of the spec does: skip when done, power > 0
                    # (RAS-03) or alpha < 1/255 (RAS-04); stop without blending (RAS-05); else
                    # blend.  Every update is an unconditional store of arithmetic that leaves
                    # the value unchanged where the lane does not blend (+ 0, * 1), not a select
                    # of the old value: LLVM would make that a masked store, and a load of the
                    # next slot from a masked store cannot take the store-forwarding path
                    # (docs/fast.md, "Speed"); the results are the same bits
                    for c in range(0 if halves & 1 else _HALF, T if halves & 2 else _HALF):
                        power = gaussian_power(A, B, Cdy2, (mx - st[_S_PX + b + c]) + lx, dy,
                                               neg_half)
                        a = min(cap, o * fast_exp(power))
                        Tc = st[_S_T + b + c]
                        test_T = Tc * (one - a)
                        live = ((st[_S_DONE + b + c] == zero) & (not (power > zero))
                                & (not (a < amin)))
                        stop = live & ((test_T <= t_min) if stop_inclusive else (test_T < t_min))
                        blend = live & (not stop)
                        stops |= stop
                        w = a * Tc
                        wb = w if blend else zero
                        st[_S_DONE + b + c] = st[_S_DONE + b + c] + (one if stop else zero)
                        st[_S_R + b + c] = st[_S_R + b + c] + cr * wb
                        st[_S_G + b + c] = st[_S_G + b + c] + cg * wb
                        st[_S_B + b + c] = st[_S_B + b + c] + cb * wb
                        st[_S_Z + b + c] = st[_S_Z + b + c] + z * wb
                        st[_S_T + b + c] = Tc * ((one - a) if blend else one)  # test_T or T
                        lst = st[_S_LAST + b + c]
                        st[_S_LAST + b + c] = lst + ((slot - lst) if blend else zero)
                    if stops:
                        done = True
                        for c in range(T):
                            done &= st[_S_DONE + b + c] != zero
                        if done:
                            live_rows &= ~(1 << r)
            s += 1
        while s < L:                             # every pixel had stopped: no later slot counts
            row_mask[start + s] = 0
            s += 1
        for r in range(nrows):
            i = ty * T + r
            for c in range(ncols):
                j = tx * T + c
                p = r * T + c
                Tc = st[_S_T + p]
                image[i, j, 0] = st[_S_R + p] + Tc * bg[0]
                image[i, j, 1] = st[_S_G + p] + Tc * bg[1]
                image[i, j, 2] = st[_S_B + p] + Tc * bg[2]
                alpha_img[i, j] = one - Tc
                depth_img[i, j] = st[_S_Z + p]
                lc = np.int32(st[_S_LAST + p])
                last_img[i, j] = lc
                n_contrib[i, j] = pos[start + lc - 1] + 1 if lc > 0 else 0
                final_T[i, j] = Tc


@njit(cache=True, nogil=True, error_model="numpy")
def composite_forward(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg, rc,
                      eps, stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib,
                      last_img, final_T, row_mask):
    """Front-to-back compositing (RAS-03..RAS-06) of the pixels of tiles [lo, hi).

    gauss/offsets/pos from refgs.fast.tiles.build_tile_lists; per-Gaussian means2d (N,2) (in D,
    or float64 for float32 compositing of float64 geometry: refgs.fast.tiles.gather), conics
    (N,3), opac (N,), colors (N,3), depths (N,); bg (3,), rc the R_* constants, eps the dtype's
    machine epsilon (float64); outputs image (H,W,3), alpha_img / depth_img / final_T (H,W) in D,
    n_contrib (H,W) int32 (1-based position in the full tile list, RAS-06, through ``pos``) and
    last_img (H,W) int32 (the same in the live list, for the backward), written for these tiles
    only.  row_mask (P,) int64: for each intersection the half rows of its tile where the screen
    kept it (refgs.fast.tiles.slot_rows; 0 for the slots after every pixel of the tile stopped),
    for the backward.
    Every operation rounded on its own (module docstring, Multiply-adds).
    """
    _forward_tiles(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg, rc, eps,
                   stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib, last_img,
                   final_T, row_mask)


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def composite_forward_fma(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg,
                          rc, eps, stop_inclusive, screen, gx, image, alpha_img, depth_img,
                          n_contrib, last_img, final_T, row_mask):
    """:func:`composite_forward` with multiply-adds fused (module docstring, Multiply-adds)."""
    _forward_tiles(lo, hi, gauss, offsets, pos, means2d, conics, opac, colors, depths, bg, rc, eps,
                   stop_inclusive, screen, gx, image, alpha_img, depth_img, n_contrib, last_img,
                   final_T, row_mask)


@njit(cache=True, inline="always", error_model="numpy")
def _backward_tiles(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                    grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth, row_mask,
                    contrib):
    """The body of :func:`composite_backward` (inlined into both variants)."""
    H, W = final_T.shape
    T = TILE_SIZE
    one, zero, neg_half, cap = rc[R_ONE], rc[R_ZERO], rc[R_NEG_HALF], rc[R_CAP]
    amin = rc[R_ALPHA_MIN]
    dt = conics.dtype                       # the compositing dtype (means2d may be float64)
    tab = np.empty((max_len(offsets, lo, hi), N_TAB), dt)
    # one slot's partial sums per gradient field and lane, over the rows
    acc = np.empty(N_GRAD_COLUMNS * T, dt)
    st = np.empty(_N_BSTATE * _NPIX, dt)
    row_last = np.empty(T, np.int32)         # per row: the largest last (list positions below)
    for tile in range(lo, hi):
        start = offsets[tile]
        L = offsets[tile + 1] - start
        ty = tile // gx
        tx = tile - ty * gx
        ncols = min(T, W - tx * T)
        nrows = min(T, H - ty * T)
        xs = centres(tx * T, tab)
        ys = centres(ty * T, tab)
        tile_last = 0
        for r in range(T):
            row_last[r] = 0
            for c in range(T):
                p = r * T + c
                if r < nrows and c < ncols:
                    i = ty * T + r
                    j = tx * T + c
                    lp = last_img[i, j]
                    Tf = final_T[i, j]
                    vr, vg, vb = v_image[i, j, 0], v_image[i, j, 1], v_image[i, j, 2]
                    vz = v_depth[i, j]
                    va = v_alpha[i, j]
                else:                                    # past the image edge: no fragments
                    lp = 0
                    Tf = vr = vg = vb = vz = va = zero
                st[_B_LAST + p] = dt.type(lp)          # exact: L <= MAX_LIST_LENGTH
                st[_B_PX + p] = xs[c]
                row_last[r] = max(row_last[r], lp)
                st[_B_T + p] = Tf
                st[_B_SUF + p] = zero
                st[_B_VR + p], st[_B_VG + p], st[_B_VB + p], st[_B_VZ + p] = vr, vg, vb, vz
                st[_B_TAIL + p] = Tf * (vr * bg[0] + vg * bg[1] + vb * bg[2] - va)
            tile_last = max(tile_last, row_last[r])
        for s in range(tile_last, L):            # behind every pixel's last blended fragment
            for f in range(N_GRAD_COLUMNS):
                contrib[start + s, f] = zero
        if tile_last == 0:
            continue
        gather(gauss, start, tile_last, means2d, conics, opac, colors, depths, tab)
        for s in range(tile_last - 1, -1, -1):   # back to front
            rows = row_mask[start + s]
            for k in range(N_GRAD_COLUMNS * T):
                acc[k] = zero
            if rows != 0:
                mx, my, A, B, C = tab[s, 0], tab[s, 1], tab[s, 2], tab[s, 3], tab[s, 4]
                o, cr, cg, cb, z = tab[s, 5], tab[s, 6], tab[s, 7], tab[s, 8], tab[s, 9]
                lx, ly = tab[s, 10], tab[s, 11]
                sf = dt.type(s)
                r_first, r_last = row_span(rows)
                for r in range(r_first, r_last + 1):
                    halves = (rows >> (2 * r)) & 3
                    if halves == 0 or s >= row_last[r]:
                        continue
                    dy = (my - ys[r]) + ly
                    Cdy2 = C * dy * dy
                    b = r * T
                    # the half rows the forward's screen kept, lanes at once, masked
                    # (vectorised); a lane is one pixel's step of the back-to-front walk: only
                    # fragments the forward blended (s < last, power <= 0, alpha >= 1/255)
                    # change T and the suffix sum or contribute (a lane of a half the screen
                    # dropped fails the alpha test, so it would add exact zeros); T and the
                    # suffix sum are stored unconditionally (* 1, + 0 elsewhere), as in the
                    # forward
                    for c in range(0 if halves & 1 else _HALF, T if halves & 2 else _HALF):
                        dx = (mx - st[_B_PX + b + c]) + lx
                        power = gaussian_power(A, B, Cdy2, dx, dy, neg_half)
                        G = fast_exp(power)
                        oG = o * G
                        a = min(cap, oG)
                        live = (sf < st[_B_LAST + b + c]) & (not (power > zero)) & (not (a < amin))
                        inv = one / (one - a)
                        Ti = st[_B_T + b + c] * inv                  # T before this fragment
                        vr, vg = st[_B_VR + b + c], st[_B_VG + b + c]
                        vb, vz = st[_B_VB + b + c], st[_B_VZ + b + c]
                        cv = cr * vr + cg * vg + cb * vb + z * vz
                        w = a * Ti
                        suf = st[_B_SUF + b + c]
                        v_a = Ti * cv - (suf + st[_B_TAIL + b + c]) * inv
                        wl = w if live else zero
                        st[_B_T + b + c] = st[_B_T + b + c] * (inv if live else one)   # Ti or T
                        st[_B_SUF + b + c] = suf + wl * cv
                        v_oG = v_a if (live & (grad_through_cap | (oG <= cap))) else zero  # RAS-10
                        v_pow = v_oG * o * G
                        g_mx = -(A * dx + B * dy) * v_pow
                        g_my = -(C * dy + B * dx) * v_pow
                        g_a = neg_half * dx * dx * v_pow
                        g_b = -dx * dy * v_pow                                        # RAS-08
                        g_c = neg_half * dy * dy * v_pow
                        # selects, not products with 0: a huge conic outside the chord could
                        # give inf * 0
                        acc[G_MX * T + c] += g_mx if live else zero
                        acc[G_MY * T + c] += g_my if live else zero
                        acc[G_A * T + c] += g_a if live else zero
                        acc[G_B * T + c] += g_b if live else zero
                        acc[G_C * T + c] += g_c if live else zero
                        acc[G_O * T + c] += v_oG * G
                        acc[G_R * T + c] += wl * vr
                        acc[G_G * T + c] += wl * vg
                        acc[G_BL * T + c] += wl * vb
                        acc[G_Z * T + c] += wl * vz
            for f in range(N_GRAD_COLUMNS):      # then the 16 lanes in a fixed order, 0..15
                total = zero
                for c in range(T):
                    total += acc[f * T + c]
                contrib[start + s, f] = total


@njit(cache=True, nogil=True, error_model="numpy")
def composite_backward(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                       grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth,
                       row_mask, contrib):
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
    saturated pixel, typically far less because the roundings do not all add up).  row_mask and
    last_img (the live-list n_contrib) are the forward's.
    Writes contrib (P, 10): row offsets[t] + s = the sum over tile t's pixels for list slot s
    (in the fixed order of the module docstring), columns G_* (means2d x, y; conic A, B,
    C; opacity; colour r, g, b; depth).  Every operation rounded on its own.
    """
    _backward_tiles(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                    grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth, row_mask,
                    contrib)


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def composite_backward_fma(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                           grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth,
                           row_mask, contrib):
    """:func:`composite_backward` with multiply-adds fused (module docstring, Multiply-adds)."""
    _backward_tiles(lo, hi, gauss, offsets, means2d, conics, opac, colors, depths, bg, rc,
                    grad_through_cap, gx, last_img, final_T, v_image, v_alpha, v_depth, row_mask,
                    contrib)


#: compositing dtype -> (forward, backward): float32 with fused multiply-adds, float64 exact
COMPOSITING_KERNELS = {np.dtype(np.float32): (composite_forward_fma, composite_backward_fma),
                       np.dtype(np.float64): (composite_forward, composite_backward)}


@njit(cache=True, nogil=True, error_model="numpy")
def reduce_by_gaussian(lo, hi, gauss, contrib, out):
    """out[g] = the sum of contrib[p] over the intersections p of a Gaussian g = gauss[p] with
    lo <= g < hi, added from 0 in intersection order (a fixed-order, race-free reduction: each
    Gaussian's sum has the same order whatever the split of [0, N) into ranges); rows lo..hi of
    out (N, 10) are zeroed first, so Gaussians without intersections get zero rows."""
    for g in range(lo, hi):
        for k in range(contrib.shape[1]):
            out[g, k] = 0.0
    for p in range(gauss.size):
        g = gauss[p]
        if lo <= g < hi:
            for k in range(contrib.shape[1]):
                out[g, k] += contrib[p, k]
