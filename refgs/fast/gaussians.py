"""Per-Gaussian stages (covariance, projection, SH colour) as fused numba kernels, forward and backward.

The same model as refgs.covariance (COV-01/02), refgs.projection (PRJ-01..PRJ-08, PRF-01..PRF-04,
PRF-08) and refgs.sh (SH-01..SH-04, CNV-09/10).  Each kernel handles a range [lo, hi) of
Gaussians (refgs.fast.render.parallel_for runs ranges on threads); no Gaussian reads another's
data, so the result does not depend on the thread count.  The expressions follow the
reference's operation order where it is cheap to do so; sums of three or four products may
associate differently from numpy's matmul/einsum (differences of a few ulp).

dtype discipline (CNV-11): every kernel is compiled once per dtype.  Literal Python floats and
ints would promote float32 arithmetic to float64 in numba, so every constant arrives in the
array ``cst`` (built by :func:`constants_array` in the Gaussians' dtype) and is read by the index
names ``K_*`` below.  Where the reference itself mixes in float64 (gsplat's radius extend and the
tile rectangles, refgs.projection.tile_rectangles), so do these kernels.

Both kernels run per block of refgs.fast.lanes.BLOCK Gaussians: what calls libm (exp, log) and
the SH colour and its gradient one Gaussian at a time, the camera frame, projection, covariance,
radius and tile rectangle -- and in the backward their gradients -- for the whole block in SIMD
lanes (refgs.fast.lanes: straight-line code LLVM vectorises across Gaussians).  The backward
*recomputes* the camera frame of each Gaussian from its raw parameters instead of storing (N,3,3)
intermediates: a few dozen flops per Gaussian, cheaper than the memory traffic.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import lanes
from .kernels import G_A, G_B, G_BL, G_C, G_G, G_MX, G_MY, G_O, G_R, G_Z
from ..constants import (ALPHA_MIN, SH_C0, SH_C1, SH_C2, SH_C3, SH_COLOR_OFFSET, TILE_SIZE,
                         Profile)

# indices into the constants array ``cst`` (all in the Gaussians' dtype)
K_ZERO, K_ONE, K_TWO, K_THREE, K_FOUR, K_SIX, K_EIGHT, K_HALF = 0, 1, 2, 3, 4, 5, 6, 7
K_NEAR, K_FAR, K_EPS2D, K_EIG_FLOOR, K_SIGMA, K_ALPHA_MIN, K_COLOR_OFFSET = 8, 9, 10, 11, 12, 13, 14
K_FX, K_FY, K_CX, K_CY, K_LNX, K_LPX, K_LNY, K_LPY = 15, 16, 17, 18, 19, 20, 21, 22
K_C0, K_C1, K_C2, K_C3 = 23, 24, 25, 30            # K_C2 .. K_C2+4, K_C3 .. K_C3+6
N_CONSTANTS = 37

# integer flags (array ``flags``)
F_NEAR_INCLUSIVE, F_DET_NONPOSITIVE, F_EIG_RULE, F_OPACITY_CULL, F_OFFSCREEN_CULL = 0, 1, 2, 3, 4
F_INRIA_TILES, F_ANTIALIASED, F_DEGREE, F_WIDTH, F_HEIGHT = 5, 6, 7, 8, 9
N_FLAGS = 10

#: the int32 ceiling of radii (HARD-11), as float64
_INT32_MAX = float(np.iinfo(np.int32).max)


def constants_array(dtype, profile: Profile, camera, lims) -> np.ndarray:
    """The constants of one render in ``dtype`` (index names K_*); ``lims`` from
    refgs.projection.frustum_limits (PRJ-03)."""
    c = np.zeros(N_CONSTANTS, np.float64)
    c[[K_ZERO, K_ONE, K_TWO, K_THREE, K_FOUR, K_SIX, K_EIGHT, K_HALF]] = [0, 1, 2, 3, 4, 6, 8, 0.5]
    c[K_NEAR], c[K_FAR], c[K_EPS2D] = profile.near, min(profile.far, np.finfo(dtype).max), profile.eps2d
    c[K_EIG_FLOOR], c[K_SIGMA], c[K_ALPHA_MIN] = profile.eig_floor, profile.radius_sigma, ALPHA_MIN
    c[K_COLOR_OFFSET] = SH_COLOR_OFFSET
    c[K_FX], c[K_FY], c[K_CX], c[K_CY] = camera.fx, camera.fy, camera.cx, camera.cy
    c[K_LNX:K_LPY + 1] = [float(v) for v in lims]
    c[K_C0], c[K_C1] = SH_C0, SH_C1
    c[K_C2:K_C2 + 5] = SH_C2
    c[K_C3:K_C3 + 7] = SH_C3
    out = c.astype(dtype)
    if not np.isfinite(profile.far):
        out[K_FAR] = np.inf
    return out


def flags_array(profile: Profile, antialiased: bool, degree: int, width: int, height: int) -> np.ndarray:
    f = np.zeros(N_FLAGS, np.int64)
    f[F_NEAR_INCLUSIVE] = profile.near_inclusive
    f[F_DET_NONPOSITIVE] = profile.det_cull_nonpositive
    f[F_EIG_RULE] = profile.radius_rule == "eig"
    f[F_OPACITY_CULL] = profile.opacity_cull
    f[F_OFFSCREEN_CULL] = profile.offscreen_cull
    f[F_INRIA_TILES] = profile.tile_rule == "inria"
    f[F_ANTIALIASED] = bool(antialiased)
    f[F_DEGREE], f[F_WIDTH], f[F_HEIGHT] = degree, width, height
    return f


# ---------------------------------------------------------------------------------------------
# shared per-Gaussian pieces (inlined into the parallel loops)
# ---------------------------------------------------------------------------------------------

@njit(cache=True, error_model="numpy")
def _sh_basis(x, y, z, deg, b, cst):
    """Basis values b[0:(deg+1)^2] of the unit direction (x, y, z) (CNV-09, SH-02)."""
    c1 = cst[K_C1]
    b[0] = cst[K_C0]
    if deg >= 1:
        b[1] = -c1 * y
        b[2] = c1 * z
        b[3] = -c1 * x
    if deg >= 2:
        xx, yy, zz = x * x, y * y, z * z
        two = cst[K_TWO]
        b[4] = cst[K_C2] * x * y
        b[5] = cst[K_C2 + 1] * y * z
        b[6] = cst[K_C2 + 2] * (two * zz - xx - yy)
        b[7] = cst[K_C2 + 3] * x * z
        b[8] = cst[K_C2 + 4] * (xx - yy)
        if deg >= 3:
            three, four = cst[K_THREE], cst[K_FOUR]
            b[9] = cst[K_C3] * y * (three * xx - yy)
            b[10] = cst[K_C3 + 1] * x * y * z
            b[11] = cst[K_C3 + 2] * y * (four * zz - xx - yy)
            b[12] = cst[K_C3 + 3] * z * (two * zz - three * xx - three * yy)
            b[13] = cst[K_C3 + 4] * x * (four * zz - xx - yy)
            b[14] = cst[K_C3 + 5] * z * (xx - yy)
            b[15] = cst[K_C3 + 6] * x * (xx - three * yy)


@njit(cache=True, error_model="numpy")
def _sh_dir_vjp(x, y, z, deg, vb, cst):
    """sum_k vb[k] d basis_k / d(x, y, z) (SH-04), the derivatives of refgs.sh.sh_basis."""
    gx = cst[K_ZERO]
    gy = cst[K_ZERO]
    gz = cst[K_ZERO]
    if deg >= 1:
        c1 = cst[K_C1]
        gy -= c1 * vb[1]
        gz += c1 * vb[2]
        gx -= c1 * vb[3]
    if deg >= 2:
        two, four = cst[K_TWO], cst[K_FOUR]
        c = K_C2
        gx += cst[c] * y * vb[4]
        gy += cst[c] * x * vb[4]
        gy += cst[c + 1] * z * vb[5]
        gz += cst[c + 1] * y * vb[5]
        gx += -two * cst[c + 2] * x * vb[6]
        gy += -two * cst[c + 2] * y * vb[6]
        gz += four * cst[c + 2] * z * vb[6]
        gx += cst[c + 3] * z * vb[7]
        gz += cst[c + 3] * x * vb[7]
        gx += two * cst[c + 4] * x * vb[8]
        gy += -two * cst[c + 4] * y * vb[8]
        if deg >= 3:
            three, six, eight = cst[K_THREE], cst[K_SIX], cst[K_EIGHT]
            xx, yy, zz = x * x, y * y, z * z
            c = K_C3
            gx += cst[c] * six * x * y * vb[9]
            gy += cst[c] * (three * xx - three * yy) * vb[9]
            gx += cst[c + 1] * y * z * vb[10]
            gy += cst[c + 1] * x * z * vb[10]
            gz += cst[c + 1] * x * y * vb[10]
            gx += -two * cst[c + 2] * x * y * vb[11]
            gy += cst[c + 2] * (four * zz - xx - three * yy) * vb[11]
            gz += eight * cst[c + 2] * y * z * vb[11]
            gx += -six * cst[c + 3] * x * z * vb[12]
            gy += -six * cst[c + 3] * y * z * vb[12]
            gz += cst[c + 3] * (six * zz - three * xx - three * yy) * vb[12]
            gx += cst[c + 4] * (four * zz - three * xx - yy) * vb[13]
            gy += -two * cst[c + 4] * x * y * vb[13]
            gz += eight * cst[c + 4] * x * z * vb[13]
            gx += two * cst[c + 5] * x * z * vb[14]
            gy += -two * cst[c + 5] * y * z * vb[14]
            gz += cst[c + 5] * (xx - yy) * vb[14]
            gx += cst[c + 6] * (three * xx - three * yy) * vb[15]
            gy += -six * cst[c + 6] * x * y * vb[15]
    return gx, gy, gz


@njit(cache=True, error_model="numpy")
def _sigmoid(x, cst):
    """1 / (1 + exp(-x)), evaluated without overflow (CNV-07)."""
    one = cst[K_ONE]
    if x >= cst[K_ZERO]:
        return one / (one + math.exp(-x))
    e = math.exp(x)
    return e / (one + e)


@njit(cache=True, nogil=True, error_model="numpy")
def gaussians_forward(lo, hi, means, log_scales, quats, logits, oscale, sh, w2c, campos, cst,
                      sigma64, flags, means2d, depths, cov2d, conics, comp, o_sig, opac, colors,
                      clamped, radii, visible, rect):
    """Covariance, projection, culling, radius, tile rectangle and SH colour of Gaussians [lo, hi).

    Inputs (N rows, dtype D): means (N,3), log_scales (N,3), quats (N,4), logits (N,),
    oscale (N,) opacity_scale (ones when None), sh (N,K,3), w2c (4,4) and campos (3,) in D,
    cst / flags, sigma64 = the radius sigma in float64 (gsplat's extend is float64 in refgs).
    Outputs written in place: means2d (N,2), depths (N,), cov2d (N,3) dilated (a,b,c), conics (N,3),
    comp (N,), o_sig (N,) sigmoid(logit), opac (N,) = o_sig*scale*comp, colors (N,3),
    clamped (N,3) bool, radii (N,2) int32, visible (N,) bool, rect (N,4) int64 (x0,x1,y0,y1).
    """
    deg = flags[F_DEGREE]
    nb = (deg + 1) * (deg + 1)
    W, H = flags[F_WIDTH], flags[F_HEIGHT]
    gx = (W + TILE_SIZE - 1) // TILE_SIZE
    gy = (H + TILE_SIZE - 1) // TILE_SIZE
    zero, one = cst[K_ZERO], cst[K_ONE]
    # the lanes' constants and camera (refgs.fast.lanes)
    cs = (zero, one, cst[K_TWO], cst[K_HALF], cst[K_EPS2D], cst[K_FX], cst[K_FY], cst[K_CX],
          cst[K_CY], cst[K_LNX], cst[K_LPX], cst[K_LNY], cst[K_LPY], cst[K_NEAR], cst[K_FAR])
    fl = (flags[F_NEAR_INCLUSIVE] != 0, flags[F_DET_NONPOSITIVE] != 0, flags[F_ANTIALIASED] != 0)
    cs_ext = (zero, cst[K_HALF], cst[K_EIG_FLOOR], cst[K_SIGMA], cst[K_ALPHA_MIN])
    fl_ext = (flags[F_EIG_RULE] != 0, flags[F_OPACITY_CULL] != 0, flags[F_INRIA_TILES] != 0,
              flags[F_OFFSCREEN_CULL] != 0)
    opacity_extent = flags[F_OPACITY_CULL] != 0 and flags[F_EIG_RULE] == 0
    dims = (W, H, gx, gy)
    w2 = lanes.camera_rows(w2c)
    # scratch, allocated once per call (not per Gaussian)
    basis = np.empty(16, means.dtype)
    L = lanes.BLOCK
    buf = np.zeros(lanes.N_FIN * L, means.dtype)
    out = np.zeros(lanes.N_FOUT * L, means.dtype)
    r64 = np.zeros(lanes.N_R64 * L, np.float64)
    ri = np.zeros(lanes.N_RI * L, np.int64)
    for g0 in range(lo, hi, L):
        nl = min(L, hi - g0)
        # per Gaussian: the calls (exp) and the SH colour (SH-01..SH-03) seen from campos =
        # -Rw^T tw; the lanes' inputs staged
        for l in range(nl):
            g = g0 + l
            for j in range(4):
                buf[(lanes.FIN_Q0 + j) * L + l] = quats[g, j]
            for j in range(3):
                buf[(lanes.FIN_M0 + j) * L + l] = means[g, j]
                buf[(lanes.FIN_S0 + j) * L + l] = math.exp(log_scales[g, j])     # COV-01
            os_ = _sigmoid(logits[g], cst)
            o_sig[g] = os_
            buf[lanes.FIN_OSIG * L + l] = os_
            buf[lanes.FIN_OSCALE * L + l] = oscale[g]
            dx = means[g, 0] - campos[0]
            dy = means[g, 1] - campos[1]
            dz = means[g, 2] - campos[2]
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not dist > zero:
                dist = one
            _sh_basis(dx / dist, dy / dist, dz / dist, deg, basis, cst)
            for ch in range(3):
                acc = zero
                for k in range(nb):
                    acc += basis[k] * sh[g, k, ch]
                rgb = acc + cst[K_COLOR_OFFSET]
                cl = rgb < zero
                clamped[g, ch] = cl
                colors[g, ch] = zero if cl else rgb
        # covariance, projection, culls, conic, compensation (PRJ-01..PRJ-04, PRJ-08): lanes
        for l in range(nl):
            lanes.projection_forward_lane(buf, out, l, w2, cs, fl)
        if opacity_extent:                   # gsplat's opacity-aware extent (PRJ-05): libm log
            for l in range(nl):
                o_eff = out[lanes.FOUT_O * L + l]
                out[lanes.FOUT_EXT * L + l] = math.sqrt(cst[K_TWO] * math.log(
                    max(o_eff, cst[K_ALPHA_MIN]) / cst[K_ALPHA_MIN]))
        # radius (PRJ-05), visibility, tile rectangle (RAS-01, PRF-08): lanes
        for l in range(nl):
            lanes.extent_lane(out, r64, ri, l, cs_ext, sigma64, fl_ext, dims)
        for l in range(nl):
            g = g0 + l
            depths[g] = out[lanes.FOUT_Z * L + l]
            means2d[g, 0] = out[lanes.FOUT_MX * L + l]
            means2d[g, 1] = out[lanes.FOUT_MY * L + l]
            for j in range(3):
                cov2d[g, j] = out[(lanes.FOUT_A + j) * L + l]
                conics[g, j] = out[(lanes.FOUT_K0 + j) * L + l]
            comp[g] = out[lanes.FOUT_CP * L + l]
            opac[g] = out[lanes.FOUT_O * L + l]
            vis = ri[lanes.RI_VIS * L + l] != 0
            visible[g] = vis
            if vis:
                radii[g, 0] = np.int32(min(r64[lanes.R64_X * L + l], _INT32_MAX))
                radii[g, 1] = np.int32(min(r64[lanes.R64_Y * L + l], _INT32_MAX))
                for j in range(4):
                    rect[g, j] = ri[(lanes.RI_X0 + j) * L + l]
            else:
                radii[g, 0] = 0
                radii[g, 1] = 0
                for j in range(4):
                    rect[g, j] = 0


# ---------------------------------------------------------------------------------------------
# backward
# ---------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, error_model="numpy")
def gaussians_backward(lo, hi, means, log_scales, quats, logits, oscale, sh, w2c, cst, flags,
                       campos, conics, comp, o_sig, clamped, visible,
                       per_g, out_means, out_log_scales, out_quats, out_logits, out_sh):
    """Backward of :func:`gaussians_forward` (COV-02, PRJ-07, PRJ-08, SH-04, CNV-07), Gaussians [lo, hi).

    per_g (N, 10): the per-Gaussian sums of the compositing backward, columns
    refgs.fast.kernels.G_* -- dL/d 2D mean, conic (off-diagonal counted once, RAS-08), opacity
    actually used, colour, depth.  campos (3,) in D.  Writes dL/d(raw parameters) into out_* (zero
    rows for culled Gaussians, zero SH coefficients above the active degree), each entry stored
    once, so output arrays of a lower precision than the stage's round once.  Mirrors
    refgs.render.render_backward.
    """
    deg = flags[F_DEGREE]
    nb = (deg + 1) * (deg + 1)
    zero, one = cst[K_ZERO], cst[K_ONE]
    # the lanes' constants and camera (refgs.fast.lanes.projection_backward_lane)
    cs = (zero, one, cst[K_TWO], cst[K_HALF], cst[K_EPS2D], cst[K_FX], cst[K_FY], cst[K_LNX],
          cst[K_LPX], cst[K_LNY], cst[K_LPY])
    w2 = lanes.camera_rows(w2c)
    aa = flags[F_ANTIALIASED] != 0
    # scratch, allocated once per call (not per Gaussian)
    basis = np.empty(16, means.dtype)
    vb = np.empty(16, means.dtype)
    L = lanes.BLOCK
    buf = np.zeros(lanes.N_IN * L, means.dtype)
    out = np.zeros(lanes.N_OUT * L, means.dtype)
    for g0 in range(lo, hi, L):
        nl = min(L, hi - g0)
        # per Gaussian: opacity, SH (SH-04) and the lanes' inputs (a lane of a culled Gaussian
        # computes on stale values; its outputs are zeros below)
        for l in range(nl):
            g = g0 + l
            for k in range(nb if visible[g] else 0, out_sh.shape[1]):    # the rest written below
                for ch in range(3):
                    out_sh[g, k, ch] = zero
            if not visible[g]:
                out_logits[g] = zero
                continue
            # opacity = sigmoid(logit) * scale * comp
            os_, sc, cp = o_sig[g], oscale[g], comp[g]
            vo = per_g[g, G_O]
            v_osig = vo * sc * cp
            out_logits[g] = v_osig * os_ * (one - os_)
            # SH-04: colour -> sh coefficients and the view direction
            dx = means[g, 0] - campos[0]
            dy = means[g, 1] - campos[1]
            dz = means[g, 2] - campos[2]
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not dist > zero:
                dist = one
            x, y, z = dx / dist, dy / dist, dz / dist
            _sh_basis(x, y, z, deg, basis, cst)
            gc0 = zero if clamped[g, 0] else per_g[g, G_R]
            gc1 = zero if clamped[g, 1] else per_g[g, G_G]
            gc2 = zero if clamped[g, 2] else per_g[g, G_BL]
            for k in range(nb):
                out_sh[g, k, 0] = basis[k] * gc0
                out_sh[g, k, 1] = basis[k] * gc1
                out_sh[g, k, 2] = basis[k] * gc2
                vb[k] = sh[g, k, 0] * gc0 + sh[g, k, 1] * gc1 + sh[g, k, 2] * gc2
            vdx, vdy, vdz = _sh_dir_vjp(x, y, z, deg, vb, cst)
            dotv = x * vdx + y * vdy + z * vdz
            buf[lanes.IN_VSX * L + l] = (vdx - x * dotv) / dist
            buf[lanes.IN_VSY * L + l] = (vdy - y * dotv) / dist
            buf[lanes.IN_VSZ * L + l] = (vdz - z * dotv) / dist
            buf[lanes.IN_VCOMP * L + l] = vo * os_ * sc
            buf[lanes.IN_CP * L + l] = cp
            for j in range(4):
                buf[(lanes.IN_Q0 + j) * L + l] = quats[g, j]
            for j in range(3):
                buf[(lanes.IN_M0 + j) * L + l] = means[g, j]
                buf[(lanes.IN_S0 + j) * L + l] = math.exp(log_scales[g, j])     # COV-01
                buf[(lanes.IN_CA + j) * L + l] = conics[g, j]
            buf[lanes.IN_VA * L + l] = per_g[g, G_A]
            buf[lanes.IN_VB * L + l] = per_g[g, G_B]
            buf[lanes.IN_VC * L + l] = per_g[g, G_C]
            buf[lanes.IN_VM0 * L + l] = per_g[g, G_MX]
            buf[lanes.IN_VM1 * L + l] = per_g[g, G_MY]
            buf[lanes.IN_VZ * L + l] = per_g[g, G_Z]
        # PRJ-07, PRJ-08, COV-02: the block's Gaussians in SIMD lanes
        for l in range(nl):
            lanes.projection_backward_lane(buf, out, l, w2, cs, aa)
        for l in range(nl):
            g = g0 + l
            vis = visible[g]
            for j in range(3):
                out_means[g, j] = out[(lanes.OUT_M0 + j) * L + l] if vis else zero
                out_log_scales[g, j] = out[(lanes.OUT_LS0 + j) * L + l] if vis else zero
            for j in range(4):
                out_quats[g, j] = out[(lanes.OUT_Q0 + j) * L + l] if vis else zero
