"""Stage 2: world -> camera -> EWA projection (2D mean, 2D covariance, conic, radius, depth).

Spec: docs/spec/stages.md clauses PRJ-01..PRJ-08 and profiles PRF-01..PRF-04, PRF-08.
Derivation of the backward: docs/derivations/projection.md.

All per-Gaussian arrays have N rows.  Culled Gaussians keep finite placeholder values and
``visible == False``; their radii are 0 and they receive no gradient.
"""
from __future__ import annotations

import numpy as np

from .constants import ALPHA_MIN, TILE_SIZE, Profile


def world_to_camera(means: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """t = R_w mean + t_w (PRJ-01).  means (N,3), world_to_camera (4,4) -> (N,3)."""
    W = np.asarray(world_to_camera, dtype=means.dtype)
    return means @ W[:3, :3].T + W[:3, 3]


def frustum_limits(camera, profile: Profile, dtype) -> tuple:
    """(lim_neg_x, lim_pos_x, lim_neg_y, lim_pos_y) on t.x/t.z and t.y/t.z (PRJ-03, PRF-02);
    infinite when ``profile.frustum_clamp`` is off (deviation no_frustum_clamp)."""
    if not profile.frustum_clamp:
        return (dtype.type(np.inf),) * 4
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    tan_x = 0.5 * camera.width / fx
    tan_y = 0.5 * camera.height / fy
    m = profile.frustum_margin
    if profile.frustum_symmetric:
        lx, ly = (1.0 + m) * tan_x, (1.0 + m) * tan_y
        lims = (lx, lx, ly, ly)
    else:
        lims = (cx / fx + m * tan_x, (camera.width - cx) / fx + m * tan_x,
                cy / fy + m * tan_y, (camera.height - cy) / fy + m * tan_y)
    return tuple(dtype.type(v) for v in lims)


def project_gaussians(means: np.ndarray, cov3d: np.ndarray, opacities: np.ndarray, camera,
                      profile: Profile, antialiased: bool = False) -> dict:
    """EWA splatting of N Gaussians into ``camera`` (PRJ-01..PRJ-08).

    means (N,3), cov3d (N,3,3), opacities (N,) activated (used by gsplat's opacity-aware radius
    and the antialiasing compensation).  Returns a dict:

      t (N,3) camera-space means; depths (N,) = t.z (PRJ-06);
      means2d (N,2) = (fx t.x/t.z + cx, fy t.y/t.z + cy) (CNV-08);
      cov2d (N,3) dilated (a, b, c); conics (N,3) = (c, -b, a)/det (PRJ-04);
      comp (N,) antialiasing compensation (1 when off, PRJ-08);
      radii (N,2) int32 (PRJ-05); visible (N,) bool; tile_rect (N,4) int (x0, x1, y0, y1), max exclusive;
      and the intermediates the backward needs (J, cov_cam, u, v, clamp flags, det).
    """
    dtype = means.dtype
    n = means.shape[0]
    Rw = np.asarray(camera.world_to_camera, dtype=dtype)[:3, :3]
    fx, fy = dtype.type(camera.fx), dtype.type(camera.fy)
    cx, cy = dtype.type(camera.cx), dtype.type(camera.cy)
    W, H = camera.width, camera.height

    t = world_to_camera(means, camera.world_to_camera)
    tz = t[:, 2]
    # PRJ-02 near/far culling
    in_depth = (tz > profile.near) if profile.near_inclusive else (tz >= profile.near)
    in_depth &= tz <= profile.far
    # placeholders keep the arithmetic finite for culled rows
    tz_safe = np.where(in_depth, tz, dtype.type(1.0))

    # CNV-08: continuous image coordinates (unclamped t)
    means2d = np.stack([fx * t[:, 0] / tz_safe + cx, fy * t[:, 1] / tz_safe + cy], axis=-1)

    # PRJ-03: Jacobian with the frustum clamp on t.x/t.z, t.y/t.z
    lnx, lpx, lny, lpy = frustum_limits(camera, profile, np.dtype(dtype))
    u_raw, v_raw = t[:, 0] / tz_safe, t[:, 1] / tz_safe
    u = np.clip(u_raw, -lnx, lpx)
    v = np.clip(v_raw, -lny, lpy)
    clamped_x = (u_raw < -lnx) | (u_raw > lpx)
    clamped_y = (v_raw < -lny) | (v_raw > lpy)
    J = np.zeros((n, 2, 3), dtype=dtype)
    J[:, 0, 0] = fx / tz_safe
    J[:, 0, 2] = -fx * u / tz_safe
    J[:, 1, 1] = fy / tz_safe
    J[:, 1, 2] = -fy * v / tz_safe

    cov_cam = Rw @ cov3d @ Rw.T
    cov2d_m = J @ cov_cam @ np.swapaxes(J, -1, -2)
    eps = dtype.type(profile.eps2d)
    a = cov2d_m[:, 0, 0] + eps                      # PRJ-04 dilation
    b = 0.5 * (cov2d_m[:, 0, 1] + cov2d_m[:, 1, 0])
    c = cov2d_m[:, 1, 1] + eps
    # conic = inverse of [[a, b], [b, c]], computed on the entries divided by m = max(a, c) so
    # that det and the eigenvalue term cannot overflow for huge splats (HARD-11)
    m = np.maximum(np.abs(a), np.abs(c))
    m = np.where(m > 0, m, dtype.type(1.0))
    a1, b1, c1 = a / m, b / m, c / m
    det1 = a1 * c1 - b1 * b1                          # det / m^2
    det_ok = (det1 > 0) if profile.det_cull_nonpositive else (det1 != 0)
    det1_safe = np.where(det_ok, det1, dtype.type(1.0))
    md = m * det1_safe                                # det / m
    conics = np.stack([c1 / md, -b1 / md, a1 / md], axis=-1)
    with np.errstate(over="ignore"):
        det = det1_safe * m * m                       # may be inf for huge splats; only reported

    # PRJ-08: gsplat's antialiasing compensation sqrt(max(0, det0 / det))
    if antialiased:
        e1 = eps / m
        det0_1 = (a1 - e1) * (c1 - e1) - b1 * b1      # det0 / m^2
        comp = np.sqrt(np.maximum(dtype.type(0.0), det0_1 / det1_safe))
        with np.errstate(over="ignore"):
            det0 = det0_1 * m * m
    else:
        det0 = None
        comp = np.ones(n, dtype=dtype)
    visible = in_depth & det_ok

    # PRJ-05: radius and tile rectangle
    if profile.radius_rule == "eig":
        # lambda_max = mid + sqrt(max(floor, mid^2 - det)), mid = (a + c)/2, in units of m
        mid1 = 0.5 * (a1 + c1)
        root = m * np.sqrt(np.maximum(mid1 * mid1 - det1, 0))
        with np.errstate(over="ignore"):
            lam1 = m * mid1 + np.maximum(np.sqrt(dtype.type(profile.eig_floor)), root)
            r = np.ceil(profile.radius_sigma * np.sqrt(np.maximum(lam1, 0)))
        rx = ry = r
    else:
        o_eff = opacities * comp
        extend = np.full(n, profile.radius_sigma, dtype=np.float64)
        if profile.opacity_cull:
            visible &= o_eff >= ALPHA_MIN
            with np.errstate(divide="ignore", invalid="ignore"):
                ext_o = np.sqrt(2.0 * np.log(np.maximum(o_eff, ALPHA_MIN) / ALPHA_MIN))
            extend = np.minimum(extend, ext_o)
        with np.errstate(over="ignore"):
            rx = np.ceil(extend * np.sqrt(np.maximum(a, 0)))
            ry = np.ceil(extend * np.sqrt(np.maximum(c, 0)))
        visible &= ~((rx <= 0) & (ry <= 0))
    rx = np.where(visible, rx, 0)
    ry = np.where(visible, ry, 0)
    tile_rect, has_tiles = tile_rectangles(means2d, rx, ry, W, H, profile)
    if profile.offscreen_cull:
        mx, my = means2d[:, 0], means2d[:, 1]
        visible &= ~((mx + rx <= 0) | (mx - rx >= W) | (my + ry <= 0) | (my - ry >= H))
    visible &= has_tiles
    # radii saturate at the int32 maximum instead of wrapping (HARD-11)
    rmax = np.iinfo(np.int32).max
    radii = np.stack([np.where(visible, np.minimum(np.asarray(rx, np.float64), rmax), 0),
                      np.where(visible, np.minimum(np.asarray(ry, np.float64), rmax), 0)], -1).astype(np.int32)
    tile_rect[~visible] = 0

    return {
        "t": t, "depths": tz, "means2d": means2d, "cov2d": np.stack([a, b, c], -1),
        "conics": conics, "comp": comp, "radii": radii, "visible": visible,
        "tile_rect": tile_rect, "J": J, "cov_cam": cov_cam, "u": u, "v": v,
        "clamped_x": clamped_x, "clamped_y": clamped_y, "tz_safe": tz_safe, "det": det,
        "det0": det0, "eps2d": eps, "profile": profile,
    }


def tile_rectangles(means2d, rx, ry, width, height, profile: Profile):
    """Tiles covered by each Gaussian, as (x0, x1, y0, y1) with x1, y1 exclusive (RAS-01, PRF-08).

    inria (getRect, auxiliary.h:46-56) works in the original's integer-centre pixel coordinates
    p = means2d - 0.5 and truncates toward zero; gsplat (IntersectTile.cu:62-77) uses
    floor(m/16 - r/16) and ceil(m/16 + r/16).  Returns ``(rect (N,4) int64, non_empty (N,) bool)``.
    """
    gx = (width + TILE_SIZE - 1) // TILE_SIZE
    gy = (height + TILE_SIZE - 1) // TILE_SIZE
    mx = means2d[:, 0].astype(np.float64)
    my = means2d[:, 1].astype(np.float64)
    rx = np.asarray(rx, np.float64)
    ry = np.asarray(ry, np.float64)
    with np.errstate(invalid="ignore"):
        if profile.tile_rule == "inria":
            px, py = mx - 0.5, my - 0.5
            x0 = np.trunc((px - rx) / TILE_SIZE)
            x1 = np.trunc((px + rx + TILE_SIZE - 1) / TILE_SIZE)
            y0 = np.trunc((py - ry) / TILE_SIZE)
            y1 = np.trunc((py + ry + TILE_SIZE - 1) / TILE_SIZE)
        else:
            x0 = np.floor(mx / TILE_SIZE - rx / TILE_SIZE)
            x1 = np.ceil(mx / TILE_SIZE + rx / TILE_SIZE)
            y0 = np.floor(my / TILE_SIZE - ry / TILE_SIZE)
            y1 = np.ceil(my / TILE_SIZE + ry / TILE_SIZE)
    big = float(max(gx, gy) + 1)
    rect = np.stack([np.clip(np.nan_to_num(x0, nan=0, posinf=big, neginf=0), 0, gx),
                     np.clip(np.nan_to_num(x1, nan=0, posinf=big, neginf=0), 0, gx),
                     np.clip(np.nan_to_num(y0, nan=0, posinf=big, neginf=0), 0, gy),
                     np.clip(np.nan_to_num(y1, nan=0, posinf=big, neginf=0), 0, gy)], -1).astype(np.int64)
    non_empty = (rect[:, 1] > rect[:, 0]) & (rect[:, 3] > rect[:, 2])
    return rect, non_empty


def project_gaussians_backward(fwd: dict, camera, v_means2d, v_conics, v_depths, v_comp=None):
    """Backward of :func:`project_gaussians` (PRJ-07, RAS-08).

    v_means2d (N,2), v_conics (N,3) with the off-diagonal counted once (dL/dB where B = conic[1]),
    v_depths (N,), v_comp (N,) or None.  Returns ``(v_means (N,3), v_cov3d (N,3,3))``; rows of
    culled Gaussians are zero.  The depth gradient under the frustum clamp is exact (the original's
    missing term, diff-gaussian-rasterization #75, is not reproduced).
    """
    dtype = fwd["t"].dtype
    vis = fwd["visible"]
    fx, fy = dtype.type(camera.fx), dtype.type(camera.fy)
    Rw = np.asarray(camera.world_to_camera, dtype=dtype)[:3, :3]
    t, tz = fwd["t"], fwd["tz_safe"]
    A, B, C = fwd["conics"][:, 0], fwd["conics"][:, 1], fwd["conics"][:, 2]
    vA, vB, vC = v_conics[:, 0], v_conics[:, 1], v_conics[:, 2]
    # Q = Sigma2D^-1 so dQ = -Q dSigma Q, written entrywise with b counted once; no division by
    # det^2, which overflows for huge splats (HARD-11)
    v_a = -(A * A * vA + A * B * vB + B * B * vC)
    v_b = -(2 * A * B * vA + (A * C + B * B) * vB + 2 * B * C * vC)
    v_c = -(B * B * vA + B * C * vB + C * C * vC)
    if v_comp is not None and fwd["det0"] is not None:
        # comp = sqrt(rho2), rho2 = det0 / det, det0 = det(Sigma2D - eps I) (PRJ-08):
        # d rho2 / da = (1 - rho2) A - eps det(Q), d rho2 / dc = (1 - rho2) C - eps det(Q),
        # d rho2 / db = 2 (1 - rho2) B
        comp = fwd["comp"]
        live = (comp > 0) & vis
        v_rho2 = np.where(live, v_comp * 0.5 / np.where(live, comp, 1), 0)
        e = fwd["eps2d"]
        rho2 = comp * comp
        detQ = A * C - B * B
        v_a += v_rho2 * ((1 - rho2) * A - e * detQ)
        v_c += v_rho2 * ((1 - rho2) * C - e * detQ)
        v_b += v_rho2 * 2 * (1 - rho2) * B
    # the dilation (+eps2d on a and c) passes the gradient straight through.
    V = np.empty((t.shape[0], 2, 2), dtype=dtype)
    V[:, 0, 0], V[:, 1, 1] = v_a, v_c
    V[:, 0, 1] = V[:, 1, 0] = 0.5 * v_b     # b appears in both symmetric entries
    J, cov_cam = fwd["J"], fwd["cov_cam"]
    v_cov_cam = np.swapaxes(J, -1, -2) @ V @ J
    v_J = 2.0 * V @ J @ cov_cam
    v_cov3d = Rw.T @ v_cov_cam @ Rw

    # J = [[fx/tz, 0, -fx u/tz], [0, fy/tz, -fy v/tz]], u = clip(tx/tz)
    u, v = fwd["u"], fwd["v"]
    free_x = ~fwd["clamped_x"]
    free_y = ~fwd["clamped_y"]
    profile = fwd.get("profile")
    if profile is not None and not profile.clamp_in_backward:   # deviation clamp_forward_only
        free_x = free_y = np.ones_like(free_x)
    v_tx = np.zeros_like(tz)
    v_ty = np.zeros_like(tz)
    v_tz = -fx / (tz * tz) * v_J[:, 0, 0] - fy / (tz * tz) * v_J[:, 1, 1]
    v_tz += fx * u / (tz * tz) * v_J[:, 0, 2] + fy * v / (tz * tz) * v_J[:, 1, 2]
    v_u = -fx / tz * v_J[:, 0, 2]
    v_v = -fy / tz * v_J[:, 1, 2]
    # u = tx/tz where not clamped
    v_tx += np.where(free_x, v_u / tz, 0)
    v_tz += np.where(free_x, -v_u * t[:, 0] / (tz * tz), 0)
    v_ty += np.where(free_y, v_v / tz, 0)
    v_tz += np.where(free_y, -v_v * t[:, 1] / (tz * tz), 0)
    if profile is not None and not profile.exact_clamp_depth_grad:
        # deviation clamp_depth_grad_original (#75): the generic 2 fx tx / tz^3 term of J02 kept
        # with the clamped tx = u tz, i.e. -v_u u / tz more on every clamped axis
        v_tz += np.where(free_x, 0, -v_u * u / tz) + np.where(free_y, 0, -v_v * v / tz)
    # means2d = (fx tx/tz + cx, fy ty/tz + cy)
    v_tx += fx / tz * v_means2d[:, 0]
    v_ty += fy / tz * v_means2d[:, 1]
    v_tz += -fx * t[:, 0] / (tz * tz) * v_means2d[:, 0] - fy * t[:, 1] / (tz * tz) * v_means2d[:, 1]
    v_tz += v_depths
    v_t = np.stack([v_tx, v_ty, v_tz], -1)
    v_means = v_t @ Rw                            # t = Rw mean + tw
    v_means[~vis] = 0
    v_cov3d[~vis] = 0
    return v_means, v_cov3d
