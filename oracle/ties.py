"""Near-ties: where a backend's threshold decisions may legitimately differ from the reference (ORC-04).

The model has steps: alpha < 1/255 skips a fragment (RAS-04), T(1 - alpha) < 1e-4 stops a pixel
(RAS-05, PRF-06), the near plane culls (PRJ-02), integer radii and tile rectangles decide coverage
(PRJ-05, RAS-01, PRF-08), the depth order decides who is in front (RAS-02).  A float32 backend
computes the continuous inputs of these decisions with relative errors of ~1e-7..1e-5, so where
the float64 reference lands *within a band* of a threshold the float32 decision may flip -- and a
flipped decision changes pixel values by far more than any rounding tolerance.

This module walks the float64 reference densely (every pixel x every Gaussian, fine for oracle
scenes) and reports, per pixel and per Gaussian, the relative distance of every such decision to
its threshold.  The oracle then (ORC-04):

* exempts pixels whose distance is inside the dtype's band from the tight forward comparison,
  **counts** them and bounds the count (tolerances.TIE_BANDS), and reports how many of them
  actually differ ("flips");
* zeroes the cotangent on them for gradient checks (a gradient is a sum over pixels, so a pixel
  with a zero cotangent contributes nothing whatever the backend decided there);
* never widens the global tolerance.

Distances are relative: |alpha / (1/255) - 1|, |T(1-alpha) / 1e-4 - 1|, |dz| / |z|, and for
per-Gaussian geometry the smallest relative perturbation (from a ladder 1e-12..1e-2) of the
projected mean, radius or depth that changes visibility, radius or tile rectangle.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

import refgs
from refgs.constants import ALPHA_MIN, T_MIN, TILE_SIZE
from refgs.projection import frustum_limits

#: perturbation ladder for per-Gaussian geometric decisions (relative sizes)
GEOM_LADDER = tuple(10.0 ** -k for k in range(12, 1, -1))
#: distance reported when no decision is within the ladder / no such decision exists
FAR = np.inf
#: per-Gaussian geometric distances above this are not mapped onto pixels (every band is far
#: below it; mapping costs a dense pixel x Gaussian pass)
GEOM_PIXEL_LIMIT = 1e-3
#: bound on |grad b_k| over the unit sphere for the SH basis functions of degree <= 3 (CNV-09):
#: the largest constant times the largest polynomial slope, rounded up (C3[1] xyz: 2.9 * 1)
SH_BASIS_SLOPE = 5.0


@dataclass
class TieDistances:
    """Relative distances of the reference's threshold decisions to their thresholds.

    Per pixel (H, W): ``alpha`` (any fragment's alpha vs 1/255), ``stop`` (any T(1-alpha) vs
    1e-4) -- both less the conditioning uncertainty (``alpha_raw``, ``stop_raw`` without it), ``depth`` (two overlapping fragments' depths), ``cap`` (o G vs the alpha cap; gradient
    only, gsplat), ``geom`` / ``clamp`` / ``shclamp`` (the smallest per-Gaussian distance of the
    Gaussians reaching the pixel), ``listgeom`` (the same over Gaussians whose tile rectangle,
    grown by a tile, holds the pixel: a coverage flip shifts list positions, hence ``n_contrib``,
    in those tiles).  Per Gaussian (N,): ``g_geom`` (visibility, tile rect), ``g_radius`` (the radii output),
    ``g_clamp`` (frustum clamp kink, gradient only), ``g_sh`` (colour clamp at 0, gradient only).
    """

    alpha: np.ndarray
    stop: np.ndarray
    depth: np.ndarray
    cap: np.ndarray
    geom: np.ndarray
    listgeom: np.ndarray
    clamp: np.ndarray
    shclamp: np.ndarray
    g_geom: np.ndarray
    g_radius: np.ndarray
    g_clamp: np.ndarray
    g_sh: np.ndarray
    cond: np.ndarray
    cond_conic: np.ndarray
    cond_cov2d: np.ndarray
    cond_means2d: np.ndarray
    cond_depths: np.ndarray
    cond_colors: np.ndarray
    cond_pixel: np.ndarray
    cond_pixel_colour: np.ndarray
    n_live: np.ndarray
    alpha_raw: np.ndarray | None = None
    stop_raw: np.ndarray | None = None

    FORWARD = ("alpha", "stop", "depth", "geom")

    def raw(self, reason: str) -> np.ndarray:
        """The distance without the conditioning reduction (what the near-tie budget counts)."""
        val = getattr(self, f"{reason}_raw", None)
        return getattr(self, reason) if val is None else val
    BACKWARD_ONLY = ("cap", "clamp", "shclamp")

    def masks(self, bands) -> dict:
        """Apply the dtype's bands (a tolerances.TieBand).  Returns ``forward`` and ``backward``
        pixel masks (H,W), ``gaussians`` (N,) with a geometric near-tie, and pixel counts per reason."""
        limit = {"alpha": bands.alpha, "stop": bands.stop, "depth": bands.depth, "geom": bands.geom,
                 "cap": bands.cap, "clamp": bands.geom, "shclamp": bands.sh}
        per = {k: getattr(self, k) <= limit[k] for k in limit}
        fwd = np.zeros_like(self.alpha, dtype=bool)
        for k in self.FORWARD:
            fwd |= per[k]
        bwd = fwd.copy()
        for k in self.BACKWARD_ONLY:
            bwd |= per[k]
        lists = fwd | (self.listgeom <= bands.geom)
        return {"forward": fwd, "backward": bwd, "lists": lists,
                "gaussians": np.minimum(self.g_geom, self.g_radius) <= bands.geom,
                "counts": {k: int(v.sum()) for k, v in per.items()},
                "closest": {k: float(np.min(getattr(self, k))) if getattr(self, k).size else FAR
                            for k in limit}}


def _permissive(profile: refgs.Profile) -> refgs.Profile:
    """The profile with every culling rule off, so every Gaussian in front gets 2D parameters."""
    return dataclasses.replace(profile, near=1e-9, near_inclusive=False, far=np.inf,
                               opacity_cull=False, offscreen_cull=False)


def _rects(mx, my, rx, ry, W, H, profile):
    """tile rectangles for arrays of any (common) shape, via refgs.tile_rectangles."""
    shape = np.shape(mx)
    m2d = np.stack([np.ravel(mx), np.ravel(my)], -1)
    rect, ok = refgs.tile_rectangles(m2d, np.ravel(rx), np.ravel(ry), W, H, profile)
    return rect.reshape(shape + (4,)), ok.reshape(shape)


def _radii(a, b, c, o_eff, profile, scale):
    """Radii (rx, ry) from the dilated (a, b, c), the continuous argument scaled by ``scale`` (PRF-04)."""
    if profile.radius_rule == "eig":
        mid = 0.5 * (a + c)
        lam1 = mid + np.sqrt(np.maximum(profile.eig_floor, mid * mid - (a * c - b * b)))
        r = np.ceil(profile.radius_sigma * np.sqrt(np.maximum(lam1, 0)) * scale)
        return r, r
    ext = np.full(np.shape(a), profile.radius_sigma)
    if profile.opacity_cull:
        with np.errstate(divide="ignore", invalid="ignore"):
            ext = np.minimum(ext, np.sqrt(2.0 * np.log(np.maximum(o_eff, ALPHA_MIN) / ALPHA_MIN)))
    return (np.ceil(ext * np.sqrt(np.maximum(a, 0)) * scale),
            np.ceil(ext * np.sqrt(np.maximum(c, 0)) * scale))


def _depth_ok(tz, profile):
    """PRJ-02: inside the profile's depth range."""
    ind = (tz > profile.near) if profile.near_inclusive else (tz >= profile.near)
    return ind & (tz <= profile.far)


def _decisions(m, a, b, c, o_eff, in_depth, W, H, profile, r_scale):
    """Visibility, radii and tile rects as the projection decides them (PRJ-05, PRF-04, PRF-08)."""
    rx, ry = _radii(a, b, c, o_eff, profile, r_scale)
    vis = in_depth.copy()
    if profile.opacity_cull:
        vis &= o_eff >= ALPHA_MIN
    if profile.radius_rule != "eig":
        vis &= ~((rx <= 0) & (ry <= 0))
    rx, ry = np.where(vis, rx, 0), np.where(vis, ry, 0)
    rect, ok = refgs.tile_rectangles(m, rx, ry, W, H, profile)
    if profile.offscreen_cull:
        mx, my = m[:, 0], m[:, 1]
        vis &= ~((mx + rx <= 0) | (mx - rx >= W) | (my + ry <= 0) | (my - ry >= H))
    vis &= ok
    rect[~vis] = 0
    return vis, np.where(vis, rx, 0), np.where(vis, ry, 0), rect


def _geometry_distance(ref, profile, p2d):
    """Per Gaussian: the smallest ladder step that flips its coverage (visibility or tile rect,
    which changes pixels), the smallest that flips its radii output (which may change nothing
    else: a huge splat's rectangle is clipped to the grid), and the tiles whose coverage flips at
    that first step, (N, gy, gx) bool (all tiles it may cover when its visibility flips).

    Every ladder step d perturbs the depth and the radius argument by a factor (1 -+ d) and the
    2D mean by -+ d (|m| + |c| + 1) pixels per axis; all 8 sign combinations are evaluated.
    """
    cam = ref.camera
    W, H = int(cam.width), int(cam.height)
    n = ref.means2d.shape[0]
    tz = p2d["depths"]
    m = p2d["means2d"]
    a, b, c = (p2d["cov2d"][:, k] for k in range(3))
    o_eff = ref.opacities
    in_depth = _depth_ok(tz, profile)
    base = _decisions(m, a, b, c, o_eff, in_depth, W, H, profile, 1.0)
    ladder = np.asarray(GEOM_LADDER)
    # variants: (L ladder steps) x (2 scale signs) x (2 x-signs) x (2 y-signs) x N
    d = ladder[:, None, None, None, None]
    s = 1 + d * np.array([-1.0, 1.0])[None, :, None, None, None]
    sx = np.array([-1.0, 1.0])[None, None, :, None, None]
    sy = np.array([-1.0, 1.0])[None, None, None, :, None]
    shape = (ladder.size, 2, 2, 2, n)
    mx = np.broadcast_to(m[:, 0] + sx * d * (np.abs(m[:, 0]) + abs(cam.cx) + 1.0), shape)
    my = np.broadcast_to(m[:, 1] + sy * d * (np.abs(m[:, 1]) + abs(cam.cy) + 1.0), shape)
    sc = np.broadcast_to(s, shape)

    def flat(x):
        return np.broadcast_to(x, shape).reshape(-1)

    alt = _decisions(np.stack([mx.reshape(-1), my.reshape(-1)], -1), flat(a), flat(b), flat(c),
                     flat(o_eff) * sc.reshape(-1), flat(in_depth), W, H, profile, sc.reshape(-1))
    cover = (alt[0].reshape(shape) != base[0]) | np.any(alt[3].reshape(shape + (4,)) != base[3], -1)
    radius = (alt[1].reshape(shape) != base[1]) | (alt[2].reshape(shape) != base[2])
    cover = cover.any(axis=(1, 2, 3))                                      # (L, N)
    radius = radius.any(axis=(1, 2, 3)) | cover
    for sgn in (-1.0, 1.0):
        cover |= _depth_ok(tz[None, :] * (1 + sgn * ladder[:, None]), profile) != in_depth[None, :]

    def first(flip):
        return np.where(flip.any(axis=0), ladder[np.argmax(flip, axis=0)], FAR)

    gx, gy = (W + TILE_SIZE - 1) // TILE_SIZE, (H + TILE_SIZE - 1) // TILE_SIZE
    tiles = np.zeros((n, gy, gx), bool)
    TX, TY = np.arange(gx), np.arange(gy)

    def covers(r):                                   # r (..., 4) -> (..., gy, gx)
        inx = (TX >= r[..., 0, None]) & (TX < r[..., 1, None])
        iny = (TY >= r[..., 2, None]) & (TY < r[..., 3, None])
        return iny[..., :, None] & inx[..., None, :]

    rects = alt[3].reshape(shape + (4,))
    for i in np.flatnonzero(cover.any(axis=0)):
        step = int(np.argmax(cover[:, i]))
        variants = rects[step, :, :, :, i].reshape(-1, 4)
        cov_v = covers(variants)
        tiles[i] = np.any(cov_v != covers(base[3][i])[None], axis=0)
        if not in_depth[i] or np.any(alt[0].reshape(shape)[step, :, :, :, i] != base[0][i]):
            tiles[i] |= np.any(cov_v, axis=0) | covers(base[3][i])   # appears / disappears
            if not tiles[i].any():
                tiles[i] = True                      # no rect known (culled by depth): all tiles
    return first(cover), first(radius), tiles


def tie_distances(ref: refgs.RenderOutput, cond_eps: float = 0.0) -> TieDistances:
    """Walk the float64 reference ``ref`` (from refgs.render) and measure every decision.

    ``cond_eps`` (the backend's COND_MARGIN * eps, 0 for none): the alpha and stop distances are
    reduced by the conditioning uncertainty of the fragment's alpha (cond_eps times the change of
    its power, see :func:`_conditioning`) and of T (the same accumulated over the fragments in
    front), so that a decision an ill-conditioned Gaussian makes uncertain counts as a near-tie.
    """
    from refgs.render import resolve_profile

    profile = resolve_profile(ref.config)
    g, cam = ref.gaussians, ref.camera
    W, H = int(cam.width), int(cam.height)
    n = len(g)
    P = W * H
    empty_px = np.full((H, W), FAR)
    if n == 0:
        z = np.zeros(0)
        return TieDistances(*(empty_px.copy() for _ in range(8)), z, z, z, z, z, z, z, z, z,
                            np.zeros((0, 3)), np.zeros((H, W)), np.zeros((H, W, 3)), z)
    cov = refgs.covariance_3d(g.quats, g.log_scales)["cov3d"]
    p2d = refgs.project_gaussians(g.means, cov, ref.opacities, cam, _permissive(profile),
                                  antialiased=False)
    g_geom, g_radius, flip_tiles = _geometry_distance(ref, profile, p2d)

    # frustum clamp kink (gradient only): distance of t.x/t.z, t.y/t.z to the limits (PRJ-03)
    lnx, lpx, lny, lpy = (float(v) for v in frustum_limits(cam, profile, np.dtype(np.float64)))
    tz = np.where(p2d["depths"] > 0, p2d["depths"], 1.0)
    ux, uy = p2d["t"][:, 0] / tz, p2d["t"][:, 1] / tz
    if np.isfinite(lnx):
        g_clamp = np.min(np.stack([np.abs(ux + lnx) / lnx, np.abs(ux - lpx) / lpx,
                                   np.abs(uy + lny) / lny, np.abs(uy - lpy) / lpy]), axis=0)
    else:                        # no frustum clamp (deviation no_frustum_clamp): no kink to meet
        g_clamp = np.full(n, FAR)
    sens = _conditioning(g, cam, p2d, (lnx, lpx, lny, lpy), ux, uy)
    # colour clamp kink (gradient only): |rgb| relative to the size of its terms (CNV-10)
    deg = ref.config.active_sh_degree(g.sh.shape[1])
    nb = (deg + 1) ** 2
    d = g.means - cam.center
    dirs = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
    basis, _ = refgs.sh_basis(deg, dirs)
    terms = basis[:, :, None] * g.sh[:, :nb, :]
    rgb = terms.sum(1) + refgs.constants.SH_COLOR_OFFSET
    g_sh = np.min(np.abs(rgb) / (np.abs(terms).sum(1) + refgs.constants.SH_COLOR_OFFSET), axis=-1)
    # colour error per unit eps: the view direction (mu - c) / |mu - c| is off by ~eps (|mu| +
    # |c|) / |mu - c|, and |grad b_k| <= SH_BASIS_SLOPE for the basis of CNV-09
    dist = np.maximum(np.linalg.norm(d, axis=-1), 1e-300)
    dir_err = (np.linalg.norm(g.means, axis=-1) + np.linalg.norm(cam.center)) / dist
    cond_colors = SH_BASIS_SLOPE * dir_err[:, None] * np.abs(g.sh[:, 1:nb, :]).sum(1)   # (N, 3)

    # dense pixel x Gaussian evaluation in reference order (RAS-01..RAS-05)
    vis = ref.visible
    order = np.lexsort((np.arange(n), ref.depths))
    order = order[vis[order]]
    rect, _ = refgs.tile_rectangles(ref.means2d, ref.radii[:, 0], ref.radii[:, 1], W, H, profile)
    rows, cols = np.divmod(np.arange(P), W)
    tx, ty = cols // TILE_SIZE, rows // TILE_SIZE
    px, py = cols + 0.5, rows + 0.5

    def fragments(idx, m2d, conics, rect_, grow=0):
        """coverage (P, n_idx) and, on covered pairs only, power and o G (RAS-01, RAS-03)."""
        r = rect_[idx]
        cov_ = ((tx[:, None] >= r[None, :, 0] - grow) & (tx[:, None] < r[None, :, 1] + grow)
                & (ty[:, None] >= r[None, :, 2] - grow) & (ty[:, None] < r[None, :, 3] + grow))
        pi, gi = np.nonzero(cov_)
        gg = idx[gi]
        dx = m2d[gg, 0] - px[pi]
        dy = m2d[gg, 1] - py[pi]
        pw = -0.5 * (conics[gg, 0] * dx * dx + conics[gg, 2] * dy * dy) - conics[gg, 1] * dx * dy
        power = np.full(cov_.shape, np.inf)
        oG = np.zeros(cov_.shape)
        sens_ = np.zeros(cov_.shape)
        power[pi, gi] = pw
        oG[pi, gi] = ref.opacities[gg] * np.exp(np.minimum(pw, 0))
        # |d power| per unit eps: conic rounding, 2D-mean and depth error (see _conditioning)
        grad = np.hypot(conics[gg, 0] * dx + conics[gg, 1] * dy, conics[gg, 1] * dx + conics[gg, 2] * dy)
        sens_[pi, gi] = (0.5 * sens["k"][gg] * (dx * dx + dy * dy) + grad * sens["dm"][gg]
                         + 2 * np.abs(pw) * sens["dz_rel"][gg])
        return cov_, power, oG, sens_

    covd, power, oG, dpow = fragments(order, ref.means2d, ref.conics, rect)
    alpha = np.minimum(profile.alpha_max, oG)
    cand = covd & (power <= 0)
    valid = cand & (alpha >= ALPHA_MIN)
    prod = np.cumprod(np.where(valid, 1 - alpha, 1.0), axis=1)
    T_before = np.concatenate([np.ones((P, 1)), prod[:, :-1]], axis=1)
    test_T = T_before * (1 - alpha)
    stops = valid & ((test_T <= T_MIN) if profile.stop_inclusive else (test_T < T_MIN))
    first_stop = np.where(stops.any(1), np.argmax(stops, axis=1), order.size) if order.size \
        else np.zeros(P, np.int64)
    upto = np.arange(order.size)[None, :] <= first_stop[:, None]
    live = valid & (np.arange(order.size)[None, :] < first_stop[:, None])

    def pmin(vals, mask):
        v = np.where(mask, vals, FAR)
        return v.min(axis=1).reshape(H, W) if v.shape[1] else empty_px.copy()

    # relative uncertainty of each fragment's alpha and of the T after it, from conditioning
    u_alpha = cond_eps * np.where(np.isfinite(dpow), dpow, 0.0)
    u_T = np.cumsum(np.where(valid, alpha / np.maximum(1 - alpha, 1e-12) * u_alpha, 0.0), axis=1)
    d_alpha = pmin(np.maximum(np.abs(alpha / ALPHA_MIN - 1) - u_alpha, 0.0), cand & upto)
    d_stop = pmin(np.maximum(np.abs(test_T / T_MIN - 1) - u_T, 0.0), valid & upto)
    d_alpha_raw = pmin(np.abs(alpha / ALPHA_MIN - 1), cand & upto)
    d_stop_raw = pmin(np.abs(test_T / T_MIN - 1), valid & upto)
    d_cap = pmin(np.abs(oG / profile.alpha_max - 1), live) if not profile.grad_through_alpha_cap \
        else empty_px.copy()
    # depth order: neighbours in the global sort that both reach the pixel (RAS-02)
    d_depth = empty_px.copy().ravel()
    z = ref.depths[order]
    near_alive = cand & (alpha >= ALPHA_MIN * 0.99)
    for k in range(order.size - 1):
        dz = abs(z[k + 1] - z[k])
        if dz == 0:                     # exact ties are broken by index: deterministic
            continue
        rel = dz / max(abs(z[k]), abs(z[k + 1]))
        both = near_alive[:, k] & near_alive[:, k + 1]
        d_depth[both] = np.minimum(d_depth[both], rel)
    d_depth = d_depth.reshape(H, W)

    # pixels a Gaussian with a geometric near-tie can change: in the tiles whose coverage flips,
    # where its alpha is near or above 1/255
    allidx = np.flatnonzero((p2d["depths"] > 0) & (g_geom <= GEOM_PIXEL_LIMIT))
    reach = np.zeros((P, n), bool)
    listed = np.zeros((P, n), bool)
    if allidx.size:
        rx2, ry2 = _reach_radius(p2d, profile)
        rect_all, _ = refgs.tile_rectangles(p2d["means2d"], rx2, ry2, W, H, profile)
        cov_a, pow_a, oG_a, _ = fragments(allidx, p2d["means2d"], p2d["conics"], rect_all, grow=1)
        in_flip = flip_tiles[allidx][:, ty, tx].T                 # (P, n_idx)
        reach[:, allidx] = cov_a & in_flip & (pow_a <= 0) & (oG_a >= ALPHA_MIN * 0.99)
        listed[:, allidx] = cov_a & in_flip
    live_full = np.zeros((P, n), bool)
    live_full[:, order] = live

    def spread(gd, where):
        v = np.where(where, gd[None, :], FAR)
        return v.min(axis=1).reshape(H, W)

    return TieDistances(alpha=d_alpha, stop=d_stop, depth=d_depth, cap=d_cap,
                        geom=spread(g_geom, reach), listgeom=spread(g_geom, listed), clamp=spread(g_clamp, live_full),
                        shclamp=spread(g_sh, live_full), g_geom=g_geom, g_radius=g_radius,
                        g_clamp=g_clamp, g_sh=g_sh, cond=sens["grad"], cond_conic=sens["conic"],
                        cond_cov2d=sens["cov2d"],
                        cond_means2d=sens["dm"], cond_depths=sens["dz"],
                        cond_colors=cond_colors,
                        cond_pixel=np.sum(np.where(live, alpha * T_before * dpow, 0.0), axis=1)
                        .reshape(H, W) if order.size else np.zeros((H, W)),
                        cond_pixel_colour=(np.where(live, alpha * T_before, 0.0) @ cond_colors[order])
                        .reshape(H, W, 3) if order.size else np.zeros((H, W, 3)),
                        n_live=live_full.sum(axis=0), alpha_raw=d_alpha_raw, stop_raw=d_stop_raw)


def _conditioning(g, cam, p2d, lims, ux, uy) -> dict:
    """Per Gaussian, per unit roundoff eps: how far rounding can move what the image depends on.

    Two mechanisms dominate (both any implementation in that dtype shares):

    * the 3D covariance, rounded, moves by ~eps s_max^2 per entry, the 2D covariance by
      ~eps s_max^2 |J|_F^2 px^2; against the dilated covariance's smallest eigenvalue that is the
      relative error c = s_max^2 |J|_F^2 / lambda_min (~1 round, up to 1e6 for needles), and the
      conic moves by k = c / lambda_min per entry (PRJ-04);
    * world -> camera, t = R mu + t_w, cancels when the Gaussian is close to a camera far from
      the origin: t is off by ~eps (|mu| + |t_w|) world units, the 2D mean by
      dm = f / z (|mu| + |t_w|) (1 + |u| + |v|) px, the depth by dz = |mu| + |t_w| (PRJ-01).

    Returns k (1/px^2), dm (px), dz (world), dz_rel = dz / z, conic = k + 2 max|conic| dz_rel
    (absolute conic error), cov2d = s_max^2 |J|_F^2 + 2 max|cov2d| dz_rel (px^2), and grad = c^2 + dm / sqrt(lambda_min) + dz_rel, the relative error of
    the Gaussian's gradients (they go through the conic twice and through the offsets d).
    """
    lnx, lpx, lny, lpy = lims
    z = np.where(p2d["depths"] > 0, p2d["depths"], 1.0)
    x, y = np.clip(ux, -lnx, lpx), np.clip(uy, -lny, lpy)
    j2 = (cam.fx ** 2 * (1 + x * x) + cam.fy ** 2 * (1 + y * y)) / (z * z)
    s2 = np.exp(2 * np.max(np.asarray(g.log_scales, np.float64), axis=1))
    a, b, c = (p2d["cov2d"][:, k] for k in range(3))
    mid = 0.5 * (a + c)
    lam_min = np.maximum(mid - np.sqrt(np.maximum(mid * mid - (a * c - b * b), 0)), 1e-12)
    cond = s2 * j2 / lam_min
    size = np.linalg.norm(np.asarray(g.means, np.float64), axis=1) + np.linalg.norm(cam.translation)
    dm = max(cam.fx, cam.fy) / z * size * (1 + np.abs(ux) + np.abs(uy))
    dz_rel = size / z
    conic_max = np.max(np.abs(p2d["conics"]), axis=1)
    k = cond / lam_min
    cov2d = s2 * j2 + 2 * np.max(np.abs(p2d["cov2d"]), axis=1) * dz_rel
    return {"k": k, "dm": dm, "dz": size, "dz_rel": dz_rel, "conic": k + 2 * conic_max * dz_rel,
            "cov2d": cov2d,
            "grad": cond ** 2 + dm / np.sqrt(lam_min) + dz_rel}


def _reach_radius(p2d, profile):
    """A generous coverage radius for every Gaussian in front (3.33 sigma of the dilated axes)."""
    a, c = p2d["cov2d"][:, 0], p2d["cov2d"][:, 2]
    r = np.ceil(3.5 * np.sqrt(np.maximum(np.maximum(a, c), 0)))
    return r, r
