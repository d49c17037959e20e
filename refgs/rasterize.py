"""Stage 4: depth sort, tile coverage and front-to-back alpha compositing, forward and backward.

Spec: docs/spec/stages.md RAS-01..RAS-10; profiles PRF-05..PRF-07.
Derivation of the backward: docs/derivations/compositing.md.

Vectorisation.  The model is per pixel and sequential (front to back); this module evaluates it
per *tile*: every tile has a depth-sorted list of the Gaussians whose tile rectangle covers it
(RAS-01, RAS-02), and all 256 pixels of a batch of tiles are evaluated against their lists at once,
padded to the longest list in the batch.  Transmittance is the running product of (1 - alpha) in
list order (``np.cumprod``, the same multiplications in the same order as the per-pixel loop),
so threshold decisions are those of the loop.  Tiles are batched by list length so that at most
``CHUNK_PAIRS`` pixel x Gaussian pairs are materialised at once (RAS-09); a list longer than that
is processed in segments carrying T across them.  Cost therefore follows the pixel-Gaussian pairs
of the covered tiles, not N x pixels.
"""
from __future__ import annotations

import numpy as np

from .constants import ALPHA_MIN, CHUNK_PAIRS, T_MIN, TILE_SIZE, Profile

PIX = TILE_SIZE * TILE_SIZE
_LOCAL_R, _LOCAL_C = np.divmod(np.arange(PIX), TILE_SIZE)


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """Number of tiles (gx, gy) covering a width x height image (RAS-01)."""
    return (width + TILE_SIZE - 1) // TILE_SIZE, (height + TILE_SIZE - 1) // TILE_SIZE


def build_tile_lists(tile_rect: np.ndarray, depths: np.ndarray, visible: np.ndarray,
                     width: int, height: int) -> dict:
    """Per-tile Gaussian lists sorted by depth, ties by Gaussian index (RAS-01, RAS-02).

    tile_rect (N,4) (x0, x1, y0, y1) exclusive max; depths (N,); visible (N,) bool.
    Returns ``{"gauss": (P,) int64, "offsets": (n_tiles+1,) int64}``: the list of tile t is
    ``gauss[offsets[t]:offsets[t+1]]``.  P is the number of (tile, Gaussian) intersections, held in
    int64 (no overflow for huge splats, hard case HARD-11).
    """
    gx, gy = tile_grid(width, height)
    n_tiles = gx * gy
    idx = np.flatnonzero(visible)
    r = tile_rect[idx].astype(np.int64)
    wx = r[:, 1] - r[:, 0]
    wy = r[:, 3] - r[:, 2]
    counts = wx * wy
    total = int(counts.sum())
    gauss = np.repeat(idx, counts)
    if total:
        starts = np.repeat(np.cumsum(counts) - counts, counts)
        k = np.arange(total, dtype=np.int64) - starts
        wxr = np.repeat(wx, counts)
        tx = np.repeat(r[:, 0], counts) + k % wxr
        ty = np.repeat(r[:, 2], counts) + k // wxr
        tile = ty * gx + tx
        order = np.lexsort((gauss, depths[gauss], tile))
        gauss, tile = gauss[order], tile[order]
    else:
        tile = np.zeros(0, np.int64)
    offsets = np.zeros(n_tiles + 1, np.int64)
    np.cumsum(np.bincount(tile, minlength=n_tiles), out=offsets[1:])
    return {"gauss": gauss.astype(np.int64), "offsets": offsets}


def _batches(lengths: np.ndarray):
    """Yield (tile ids, segment start, segment length) covering all non-empty tiles (RAS-09)."""
    order = np.argsort(lengths, kind="stable")
    order = order[lengths[order] > 0]
    max_seg = max(1, CHUNK_PAIRS // PIX)
    i = 0
    while i < order.size:
        L = int(lengths[order[i]])
        if L > max_seg:                         # one long list: segments along the list
            for s in range(0, L, max_seg):
                yield order[i:i + 1], s, min(max_seg, L - s), s + max_seg >= L
            i += 1
            continue
        # grow the batch while the padded size fits
        j = i + 1
        while j < order.size and (j - i + 1) * PIX * int(lengths[order[j]]) <= CHUNK_PAIRS:
            j += 1
        yield order[i:j], 0, int(lengths[order[j - 1]]), True
        i = j


#: Safety factor on the rounding-error bound of the candidate screen (a few ulps per term).
_SCREEN_ULPS = 64.0


def _pixel_features() -> np.ndarray:
    """(256, 6) features [1, x, y, x^2, y^2, x y] of the tile-local pixel centres."""
    x = _LOCAL_C + 0.5
    y = _LOCAL_R + 0.5
    return np.stack([np.ones(PIX), x, y, x * x, y * y, x * y], axis=-1)


_FEATURES = _pixel_features()


class _Batch:
    """Pixel x Gaussian quantities of one batch of tiles (B tiles, P = 256 pixels).

    Two steps.  (1) *Screen*: a conservative candidate test for every (pixel, list slot) pair,
    using the Gaussian's power expanded as a quadratic form in tile-local coordinates (one batched
    matrix product) -- this only decides which pairs are evaluated, never a value.  (2) *Exact
    evaluation* of the candidates, compacted per pixel in list order to (B, P, V) with V the
    largest candidate count of a pixel in the batch: power, G, alpha, the skips and the running
    transmittance exactly as in the per-pixel loop (RAS-03..RAS-05).  A pair rejected by the screen
    has alpha < 1/255 by a margin larger than the screen's rounding-error bound, so the result is
    that of evaluating every pair.
    """

    def __init__(self, tiles, seg_start, seg_len, lists, g2d, width, height, profile, T_in, done_in):
        gx, _ = tile_grid(width, height)
        offsets, gauss = lists["offsets"], lists["gauss"]
        starts = offsets[tiles] + seg_start
        lens = np.minimum(offsets[tiles + 1] - starts, seg_len)
        slot = np.arange(seg_len)
        present = slot[None, :] < lens[:, None]                             # (B, L)
        gid_l = np.where(present, gauss[np.minimum(starts[:, None] + slot, max(gauss.size - 1, 0))], 0)
        ty, tx = np.divmod(tiles, gx)
        self.rows = ty[:, None] * TILE_SIZE + _LOCAL_R[None, :]              # (B, P)
        self.cols = tx[:, None] * TILE_SIZE + _LOCAL_C[None, :]
        self.inside = (self.rows < height) & (self.cols < width)
        dt = g2d["means2d"].dtype

        # (1) screen, in float64 and tile-local coordinates
        ox = (tx * TILE_SIZE).astype(np.float64)[:, None]
        oy = (ty * TILE_SIZE).astype(np.float64)[:, None]
        mx = g2d["means2d"][gid_l, 0].astype(np.float64) - ox               # (B, L)
        my = g2d["means2d"][gid_l, 1].astype(np.float64) - oy
        shift = 0.5 - profile.pixel_offset       # the features sit at +0.5 (deviation pixel_centre_0)
        if shift:
            mx, my = mx + shift, my + shift
        A, Bc, C = (g2d["conics"][gid_l, i].astype(np.float64) for i in range(3))
        o = g2d["opacities"][gid_l].astype(np.float64)
        Q = np.stack([-0.5 * A * mx * mx - 0.5 * C * my * my - Bc * mx * my,
                      A * mx + Bc * my, C * my + Bc * mx, -0.5 * A, -0.5 * C, -Bc], axis=1)
        approx = np.einsum("pk,bkl->bpl", _FEATURES, Q, optimize=True)       # (B, P, L)
        span = np.abs(mx) + np.abs(my) + 2 * TILE_SIZE
        margin = _SCREEN_ULPS * np.finfo(np.float64).eps * (1 + (np.abs(A) + np.abs(Bc) + np.abs(C)) * span * span)
        margin += _SCREEN_ULPS * np.finfo(dt).eps * (1 + np.log(255.0) + np.abs(np.log(np.maximum(o, 1e-300))))
        with np.errstate(divide="ignore"):
            thr = np.where(o > 0, np.log(ALPHA_MIN / np.maximum(o, 1e-300)), np.inf)
        if not profile.alpha_skip:               # deviation alpha_skip_off: every pair is a candidate
            thr = np.full_like(thr, -np.inf)
        cand = approx >= (thr - margin)[:, None, :]
        cand &= approx <= margin[:, None, :]
        cand &= present[:, None, :]
        cand &= self.inside[:, :, None]

        # compaction: per pixel, candidate slots in list order
        nb, L = cand.shape[0], cand.shape[-1]
        counts = np.count_nonzero(cand, axis=-1).ravel()                    # (B*P,)
        V = max(int(counts.max()) if counts.size else 0, 1)
        flat = np.flatnonzero(cand)
        row, li = np.divmod(flat, L)
        slot_k = np.arange(flat.size) - np.repeat(np.cumsum(counts) - counts, counts)
        lidx = np.full((nb * PIX, V), -1, np.int64)
        lidx[row, slot_k] = li
        lidx = lidx.reshape(nb, PIX, V)
        has = lidx >= 0
        lsafe = np.where(has, lidx, 0)
        fi = (np.arange(nb)[:, None, None] * L + lsafe).ravel()             # flat (tile, slot)
        self.gid = np.take(gid_l.ravel(), fi).reshape(lsafe.shape)           # (B, P, V)
        self.pos = seg_start + lsafe                                         # 0-based list position

        # (2) exact evaluation in the Gaussians' dtype; one gather of a per-slot table
        table = np.concatenate([g2d["means2d"][gid_l], g2d["conics"][gid_l],
                                g2d["opacities"][gid_l][..., None]], axis=-1)   # (B, L, 6)
        vals = np.take(table.reshape(nb * L, 6), fi, axis=0).reshape(lsafe.shape + (6,))
        px = (self.cols + profile.pixel_offset).astype(dt)[:, :, None]      # CNV-08 pixel centres
        py = (self.rows + profile.pixel_offset).astype(dt)[:, :, None]
        self.dx = vals[..., 0] - px                                          # d = mean - pixel
        self.dy = vals[..., 1] - py
        self.A, self.B, self.C, self.o = vals[..., 2], vals[..., 3], vals[..., 4], vals[..., 5]
        power = -0.5 * (self.A * self.dx * self.dx + self.C * self.dy * self.dy) \
            - self.B * self.dx * self.dy                                     # RAS-03
        valid = has & (power <= 0)
        self.G = np.exp(np.minimum(power, 0))
        self.oG = self.o * self.G
        self.alpha = np.minimum(dt.type(profile.alpha_max), self.oG)         # RAS-04
        if profile.alpha_skip:
            valid &= self.alpha >= ALPHA_MIN
        one_minus = np.where(valid, 1 - self.alpha, 1)
        # running transmittance in list order: the same products in the same order as the
        # per-pixel loop (RAS-05); a carried T_in goes first so the association is the loop's
        if np.all(T_in == 1):
            incl = np.cumprod(one_minus, axis=-1)
        else:
            incl = np.cumprod(np.concatenate([T_in[:, :, None], one_minus], -1), -1)[..., 1:]
        keep = (incl > T_MIN) if profile.stop_inclusive else (incl >= T_MIN)
        if profile.transmittance_stop == "before":                           # RAS-05
            self.blended = valid & keep & ~done_in[:, :, None]
            self.done_out = done_in | np.any(valid & ~keep, axis=-1)
        elif profile.transmittance_stop == "after":      # deviation blend_at_cutoff
            before = np.concatenate([np.ones_like(keep[..., :1]), keep[..., :-1]], -1)
            self.blended = valid & before & ~done_in[:, :, None]
            self.done_out = done_in | np.any(valid & ~keep, axis=-1)
        else:                                             # deviation stop_off
            self.blended = valid & ~done_in[:, :, None]
            self.done_out = done_in
        self.T = np.empty_like(incl)                                         # T before each slot
        self.T[..., 0] = T_in
        self.T[..., 1:] = incl[..., :-1]
        last = V - 1 - np.argmax(self.blended[..., ::-1], axis=-1)
        any_b = self.blended.any(axis=-1)
        self.last_pos = np.where(any_b, np.take_along_axis(self.pos, last[..., None], -1)[..., 0] + 1, 0)
        self.T_out = np.where(any_b, np.take_along_axis(incl, last[..., None], -1)[..., 0], T_in)
        self.w = np.where(self.blended, self.alpha * self.T, 0)             # weights a_i T_i


def _init_carry(tiles, dt):
    return np.ones((tiles.size, PIX), dt), np.zeros((tiles.size, PIX), bool)


def _background(background, dt, profile: Profile, factor: float = 1.0) -> np.ndarray:
    """The background as the image adds it (RAS-06): zero without ``profile.background_term``
    (deviation no_background); times ``factor`` in the backward (deviation background_grad_doubled)."""
    bg = np.asarray(background, dt)
    if not profile.background_term:
        return np.zeros_like(bg)
    return bg * dt.type(factor) if factor != 1 else bg


def composite(g2d: dict, lists: dict, width: int, height: int, profile: Profile,
              background: np.ndarray) -> dict:
    """Front-to-back compositing of every pixel (RAS-03..RAS-06).

    g2d: per-Gaussian ``means2d`` (N,2), ``conics`` (N,3), ``opacities`` (N,), ``colors`` (N,3),
    ``depths`` (N,).  lists: from :func:`build_tile_lists`.  background (3,).
    Returns image (H,W,3) = sum c a T + T_final bg, alpha (H,W) = 1 - T_final, depth (H,W) =
    sum z a T, n_contrib (H,W) int32, final_T (H,W).
    """
    dt = g2d["means2d"].dtype
    C = np.zeros((height, width, 3), dt)
    D = np.zeros((height, width), dt)
    T_final = np.ones((height, width), dt)
    last = np.zeros((height, width), np.int32)
    lengths = np.diff(lists["offsets"])
    carry = {}
    for tiles, s0, sl, _ in _batches(lengths):
        key = int(tiles[0])
        T_in, done_in = carry.get(key, _init_carry(tiles, dt))
        b = _Batch(tiles, s0, sl, lists, g2d, width, height, profile, T_in, done_in)
        if tiles.size == 1 and s0 + sl < lengths[key]:
            carry[key] = (b.T_out, b.done_out)
        r, c, ins = b.rows[b.inside], b.cols[b.inside], b.inside
        C[r, c] += np.einsum("bpv,bpvc->bpc", b.w, g2d["colors"][b.gid])[ins]
        D[r, c] += np.sum(b.w * g2d["depths"][b.gid], axis=-1)[ins]
        T_final[r, c] = b.T_out[ins]
        last[r, c] = np.maximum(last[r, c], b.last_pos[ins])
    image = C + T_final[..., None] * _background(background, dt, profile)
    return {"image": image, "alpha": 1 - T_final, "depth": D, "n_contrib": last, "final_T": T_final}


def composite_backward(g2d: dict, lists: dict, width: int, height: int, profile: Profile,
                       background: np.ndarray, final_T: np.ndarray, v_image: np.ndarray,
                       v_alpha: np.ndarray | None, v_depth: np.ndarray | None) -> dict:
    """Backward of :func:`composite` (RAS-07, RAS-08, RAS-10).

    Recomputes every batch exactly as the forward, then for each blended Gaussian i of a pixel
    (T_i = transmittance before it, w_j = a_j T_j):

      dL/dc_i     = a_i T_i dL/dC
      dL/da_i     = T_i (c_i . dL/dC + z_i dL/dD) - back_i / (1 - a_i),
      back_i      = sum_{j behind i} w_j (c_j . dL/dC + z_j dL/dD) + T_final (bg . dL/dC - dL/dalpha)

    where the suffix sum walks the list back to front.  Then a = min(cap, o G) (RAS-10),
    G = exp(power), and power's gradient goes to the conic with the off-diagonal counted once
    (dL/dB = -dx dy G dL/dG, RAS-08) and to the 2D mean in pixels.
    Returns per-Gaussian sums: v_means2d (N,2), v_conics (N,3), v_opacities (N,), v_colors (N,3),
    v_depths (N,).
    """
    dt = g2d["means2d"].dtype
    n = g2d["means2d"].shape[0]
    bg = _background(background, dt, profile, profile.background_grad_factor)
    v_alpha = np.zeros((height, width), dt) if v_alpha is None else v_alpha
    v_depth = np.zeros((height, width), dt) if v_depth is None else v_depth
    cols = {"mx": 0, "my": 1, "A": 2, "B": 3, "C": 4, "o": 5, "r": 6, "g": 7, "b": 8, "z": 9}
    acc = np.zeros((n, len(cols)), dt)
    lengths = np.diff(lists["offsets"])
    # segments of one long list are visited back to front for the suffix sums: first replay the
    # forward carries, then walk the batches in reverse.
    batches = list(_batches(lengths))
    seg_inputs, carry = {}, {}
    for tiles, s0, sl, _ in batches:
        key = int(tiles[0])
        seg_inputs[(key, s0)] = carry.get(key, _init_carry(tiles, dt))
        if tiles.size == 1 and s0 + sl < lengths[key]:
            b = _Batch(tiles, s0, sl, lists, g2d, width, height, profile, *seg_inputs[(key, s0)])
            carry[key] = (b.T_out, b.done_out)
    back_carry = {}
    for tiles, s0, sl, _ in reversed(batches):
        key = int(tiles[0])
        b = _Batch(tiles, s0, sl, lists, g2d, width, height, profile, *seg_inputs[(key, s0)])
        rr = np.minimum(b.rows, height - 1)
        cc = np.minimum(b.cols, width - 1)
        ins = b.inside
        vC = np.where(ins[..., None], v_image[rr, cc], 0)                    # (B,P,3)
        vD = np.where(ins, v_depth[rr, cc], 0)
        vA = np.where(ins, v_alpha[rr, cc], 0)
        Tf = np.where(ins, final_T[rr, cc], 0)
        col = g2d["colors"][b.gid]                                          # (B,P,V,3)
        z = g2d["depths"][b.gid]                                            # (B,P,V)
        cv = np.einsum("bpvc,bpc->bpv", col, vC) + z * vD[..., None]
        q = b.w * cv
        # exclusive suffix sums, back to front; the tail comes from later segments of the list
        tail = back_carry.get(key, np.zeros_like(vD))
        suffix = np.cumsum(q[..., ::-1], axis=-1)[..., ::-1] - q + tail[..., None]
        if tiles.size == 1 and s0 > 0:
            back_carry[key] = suffix[..., 0] + q[..., 0]
        back = suffix + (Tf * (np.einsum("bpc,c->bp", vC, bg) - vA))[..., None]
        v_a = np.where(b.blended, b.T * cv - back / (1 - b.alpha), 0)
        if profile.grad_through_alpha_cap:
            v_oG = v_a
        else:
            v_oG = np.where(b.oG <= profile.alpha_max, v_a, 0)
        v_pow = v_oG * b.o * b.G                                            # dL/dpower
        dx, dy = b.dx, b.dy
        sel = b.blended
        gid = b.gid[sel]
        v_mx = -(b.A * dx + b.B * dy) * v_pow                               # 2D mean, pixels
        v_my = -(b.C * dy + b.B * dx) * v_pow
        v_Acon = -0.5 * dx * dx * v_pow                                     # conic, RAS-08:
        v_Bcon = -dx * dy * v_pow                                           # off-diagonal once
        if profile.conic_offdiag_grad_factor != 1:       # deviation conic_offdiag_doubled
            v_Bcon = v_Bcon * profile.conic_offdiag_grad_factor
        v_Ccon = -0.5 * dy * dy * v_pow
        v_o = v_oG * b.G
        v_col = b.w[..., None] * vC[:, :, None, :]
        v_z = b.w * vD[..., None]
        parts = np.stack([v_mx[sel], v_my[sel], v_Acon[sel], v_Bcon[sel], v_Ccon[sel], v_o[sel],
                          *v_col[sel].T, v_z[sel]], axis=-1)
        for k in range(parts.shape[1]):
            acc[:, k] += np.bincount(gid, weights=parts[:, k], minlength=n)
    return {"v_means2d": acc[:, 0:2], "v_conics": acc[:, 2:5], "v_opacities": acc[:, 5],
            "v_colors": acc[:, 6:9], "v_depths": acc[:, 9]}
