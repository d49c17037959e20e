"""Per-Gaussian arithmetic evaluated across Gaussians, in SIMD lanes (numba kernels' pieces).

A loop that takes one Gaussian at a time compiles to scalar float code, with a few dozen
intermediate values per Gaussian.  Where that arithmetic is straight-line, refgs.fast.gaussians
evaluates it through this module for a *block* of BLOCK Gaussians at once: it stages each input
of the block as a field of one scratch array (``buf[F * BLOCK + l]`` for Gaussian l of the
block), runs the lane function in a loop over l, and copies the output fields of a second
scratch array to its outputs.  The loop then reads and writes only those scratch arrays (LLVM
needs one run-time alias check, not one per input and output array), its body is one basic block
(every choice a select of two computed values, no branch with arithmetic in it, no call: the
min/max builtins are spelled as selects), and LLVM vectorises it across Gaussians (16 float32
lanes in a zmm register on AVX-512 machines, 8 in ymm elsewhere).

Every value is computed in the Gaussians' dtype (float64 where the spec's rectangle maths is),
each expression in a fixed operation order (a change of order changes refgs.fast's bits); both
arms of a choice are computed and one is selected, which gives the value the branch would.  Calls
the vectoriser cannot take (exp and log from libm) stay in the caller's per-Gaussian loop, which
stages their results.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..constants import TILE_SIZE

#: Gaussians per block: the lane loop's trip count (a multiple of the widest vector, 16 float32
#: lanes, so that only a range's last block runs a remainder); the scratch arrays, 24 + 10 fields
#: of BLOCK values, stay in L1
BLOCK = 64
#: input fields of :func:`projection_backward_lane`: the raw quaternion, mean and scales
#: (exp(log-scale), staged by the caller), the conic, dL/d conic (A, B, C), dL/d 2D mean, dL/d
#: depth, the antialiasing compensation and dL/d compensation, and the view direction's part of
#: dL/d mean (SH-04)
(IN_Q0, IN_Q1, IN_Q2, IN_Q3, IN_M0, IN_M1, IN_M2, IN_S0, IN_S1, IN_S2, IN_CA, IN_CB, IN_CC,
 IN_VA, IN_VB, IN_VC, IN_VM0, IN_VM1, IN_VZ, IN_CP, IN_VCOMP, IN_VSX, IN_VSY, IN_VSZ) = range(24)
N_IN = 24
#: output fields: dL/d mean, d log-scale, d quaternion
(OUT_M0, OUT_M1, OUT_M2, OUT_LS0, OUT_LS1, OUT_LS2, OUT_Q0, OUT_Q1, OUT_Q2, OUT_Q3) = range(10)
N_OUT = 10
#: the forward's input fields (:func:`projection_forward_lane`): raw quaternion, mean, scales
#: (staged exp(log-scale)), sigmoid(logit) and the opacity scale
(FIN_Q0, FIN_Q1, FIN_Q2, FIN_Q3, FIN_M0, FIN_M1, FIN_M2, FIN_S0, FIN_S1, FIN_S2, FIN_OSIG,
 FIN_OSCALE) = range(12)
N_FIN = 12
#: the forward's per-lane results: depth, 2D mean, dilated 2D covariance, conic, compensation,
#: opacity used, the scaled entries and determinant the radius needs, in-depth-and-det flag (0 /
#: 1), and the caller's staged opacity extent (gsplat's opacity cull: sqrt(2 ln(o / (1/255))))
(FOUT_Z, FOUT_MX, FOUT_MY, FOUT_A, FOUT_B, FOUT_C, FOUT_K0, FOUT_K1, FOUT_K2, FOUT_CP, FOUT_O,
 FOUT_A1, FOUT_C1, FOUT_DET1, FOUT_M, FOUT_VIS, FOUT_EXT) = range(17)
N_FOUT = 17
#: the extent's results (:func:`extent_lane`): radii in float64 and the tile rectangle and
#: visibility as integers
(R64_X, R64_Y) = range(2)
N_R64 = 2
(RI_X0, RI_X1, RI_Y0, RI_Y1, RI_VIS) = range(5)
N_RI = 5
#: the tile edge as float64, for the rectangle maths
_TILE = float(TILE_SIZE)


@njit(cache=True, inline="always", error_model="numpy")
def _clip(a, lo, hi):
    """min(max(a, lo), hi), as the builtins give it, in selects (the builtins are calls when the
    vectoriser runs)."""
    b = lo if lo > a else a
    return hi if hi < b else b


@njit(cache=True, inline="always", error_model="numpy")
def camera_rows(w2c):
    """The world-to-camera matrix's first three rows as 12 scalars, row-major (the lanes' w2)."""
    return (w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[0, 3], w2c[1, 0], w2c[1, 1], w2c[1, 2],
            w2c[1, 3], w2c[2, 0], w2c[2, 1], w2c[2, 2], w2c[2, 3])


@njit(cache=True, inline="always", error_model="numpy")
def camera_frame(q0, q1, q2, q3, m0, m1, m2, S0, S1, S2, w2, zero, one, two):
    """Unit quaternion, rotation, M = R diag(S), camera-frame mean t and covariance
    Cc = Rw M M^T Rw^T of one lane (COV-01, CNV-04, CNV-05, PRJ-01), as a tuple: (w, x, y, z,
    |q|, R (9, row-major), M (9), t (3), Cc (9)).  q is divided by max |q_k| before it is
    normalised (CNV-05); Sigma = M M^T, then Cc = Rw Sigma Rw^T as (Rw Sigma) Rw^T."""
    (w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23) = w2
    # max |q_k| in selects (the builtin is a call where the vectoriser runs)
    a0, a1, a2, a3 = abs(q0), abs(q1), abs(q2), abs(q3)
    m01 = a1 if a1 > a0 else a0
    m23 = a3 if a3 > a2 else a2
    m = m23 if m23 > m01 else m01
    safe = m if m > zero else one
    w, x, y, z = q0 / safe, q1 / safe, q2 / safe, q3 / safe
    ns = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / ns, x / ns, y / ns, z / ns
    qn = ns * safe
    # CNV-04
    R00 = one - two * (y * y + z * z)
    R01 = two * (x * y - w * z)
    R02 = two * (x * z + w * y)
    R10 = two * (x * y + w * z)
    R11 = one - two * (x * x + z * z)
    R12 = two * (y * z - w * x)
    R20 = two * (x * z - w * y)
    R21 = two * (y * z + w * x)
    R22 = one - two * (x * x + y * y)
    M00, M01, M02 = R00 * S0, R01 * S1, R02 * S2
    M10, M11, M12 = R10 * S0, R11 * S1, R12 * S2
    M20, M21, M22 = R20 * S0, R21 * S1, R22 * S2
    t0 = w00 * m0 + w01 * m1 + w02 * m2 + w03
    t1 = w10 * m0 + w11 * m1 + w12 * m2 + w13
    t2 = w20 * m0 + w21 * m1 + w22 * m2 + w23
    s00 = M00 * M00 + M01 * M01 + M02 * M02
    s01 = M00 * M10 + M01 * M11 + M02 * M12
    s02 = M00 * M20 + M01 * M21 + M02 * M22
    s10 = M10 * M00 + M11 * M01 + M12 * M02
    s11 = M10 * M10 + M11 * M11 + M12 * M12
    s12 = M10 * M20 + M11 * M21 + M12 * M22
    s20 = M20 * M00 + M21 * M01 + M22 * M02
    s21 = M20 * M10 + M21 * M11 + M22 * M12
    s22 = M20 * M20 + M21 * M21 + M22 * M22
    p00 = w00 * s00 + w01 * s10 + w02 * s20
    p01 = w00 * s01 + w01 * s11 + w02 * s21
    p02 = w00 * s02 + w01 * s12 + w02 * s22
    p10 = w10 * s00 + w11 * s10 + w12 * s20
    p11 = w10 * s01 + w11 * s11 + w12 * s21
    p12 = w10 * s02 + w11 * s12 + w12 * s22
    p20 = w20 * s00 + w21 * s10 + w22 * s20
    p21 = w20 * s01 + w21 * s11 + w22 * s21
    p22 = w20 * s02 + w21 * s12 + w22 * s22
    C00 = p00 * w00 + p01 * w01 + p02 * w02
    C01 = p00 * w10 + p01 * w11 + p02 * w12
    C02 = p00 * w20 + p01 * w21 + p02 * w22
    C10 = p10 * w00 + p11 * w01 + p12 * w02
    C11 = p10 * w10 + p11 * w11 + p12 * w12
    C12 = p10 * w20 + p11 * w21 + p12 * w22
    C20 = p20 * w00 + p21 * w01 + p22 * w02
    C21 = p20 * w10 + p21 * w11 + p22 * w12
    C22 = p20 * w20 + p21 * w21 + p22 * w22
    return (w, x, y, z, qn, R00, R01, R02, R10, R11, R12, R20, R21, R22,
            M00, M01, M02, M10, M11, M12, M20, M21, M22, t0, t1, t2,
            C00, C01, C02, C10, C11, C12, C20, C21, C22)


@njit(cache=True, inline="always", error_model="numpy")
def projection_backward_lane(buf, out, l, w2, cs, aa):
    """Lane l of a block: the camera frame (COV-01, PRJ-01) recomputed from the lane's inputs in
    ``buf`` (IN_* fields), then the projection, covariance and quaternion backward (PRJ-07,
    PRJ-08, COV-02, CNV-05) into ``out`` (OUT_* fields): dL/d mean (with the view direction's
    part IN_VSX..), d log-scale, d quaternion.  w2 = the world-to-camera matrix's first three
    rows (12 values, row-major), cs = (0, 1, 2, 1/2, eps2d, fx, fy, and the clamp limits of
    PRJ-03: lim_x-, lim_x+, lim_y-, lim_y+) in the dtype, aa = antialiased (PRJ-08).  The
    Jacobian takes the unclamped tz here (the forward's in-depth substitute does not enter the
    backward), the conic's gradient is -Q dSigma Q with b counted once (refgs.projection)."""
    L = BLOCK
    (zero, one, two, half, eps, fx, fy, lnx, lpx, lny, lpy) = cs
    (w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23) = w2
    S0, S1, S2 = buf[IN_S0 * L + l], buf[IN_S1 * L + l], buf[IN_S2 * L + l]
    (w, x, y, z, qn, R00, R01, R02, R10, R11, R12, R20, R21, R22,
     M00, M01, M02, M10, M11, M12, M20, M21, M22, t0, t1, t2,
     C00, C01, C02, C10, C11, C12, C20, C21, C22) = camera_frame(
        buf[IN_Q0 * L + l], buf[IN_Q1 * L + l], buf[IN_Q2 * L + l], buf[IN_Q3 * L + l],
        buf[IN_M0 * L + l], buf[IN_M1 * L + l], buf[IN_M2 * L + l], S0, S1, S2, w2, zero, one, two)
    # PRJ-03: the clamped EWA Jacobian
    tz = t2
    u_raw = t0 / tz
    v_raw = t1 / tz
    u = _clip(u_raw, -lnx, lpx)
    v = _clip(v_raw, -lny, lpy)
    clx = (u_raw < -lnx) | (u_raw > lpx)
    cly = (v_raw < -lny) | (v_raw > lpy)
    j00, j02, j11, j12 = fx / tz, -fx * u / tz, fy / tz, -fy * v / tz
    A, B, C = buf[IN_CA * L + l], buf[IN_CB * L + l], buf[IN_CC * L + l]
    vA, vB, vC = buf[IN_VA * L + l], buf[IN_VB * L + l], buf[IN_VC * L + l]
    va = -(A * A * vA + A * B * vB + B * B * vC)
    vbb = -(two * A * B * vA + (A * C + B * B) * vB + two * B * C * vC)
    vc = -(B * B * vA + B * C * vB + C * C * vC)
    cp = buf[IN_CP * L + l]
    v_rho2 = buf[IN_VCOMP * L + l] * half / cp
    rho2 = cp * cp
    det_q = A * C - B * B
    anti = aa & (cp > zero)
    # both arms computed, then selected (a branch with arithmetic in an arm stops LLVM's
    # vectoriser; the unused arm is discarded, which gives the value the branch would)
    va_a = va + v_rho2 * ((one - rho2) * A - eps * det_q)
    vc_a = vc + v_rho2 * ((one - rho2) * C - eps * det_q)
    vbb_a = vbb + v_rho2 * two * (one - rho2) * B
    va = va_a if anti else va
    vc = vc_a if anti else vc
    vbb = vbb_a if anti else vbb
    V01 = half * vbb
    # Jm = [[j00, 0, j02], [0, j11, j12]]
    VJ00 = va * j00 + V01 * zero
    VJ01 = va * zero + V01 * j11
    VJ02 = va * j02 + V01 * j12
    VJ10 = V01 * j00 + vc * zero
    VJ11 = V01 * zero + vc * j11
    VJ12 = V01 * j02 + vc * j12
    # vCc[i, j] = Jm[0, i] VJ[0, j] + Jm[1, i] VJ[1, j]
    v00 = j00 * VJ00 + zero * VJ10
    v01 = j00 * VJ01 + zero * VJ11
    v02 = j00 * VJ02 + zero * VJ12
    v10 = zero * VJ00 + j11 * VJ10
    v11 = zero * VJ01 + j11 * VJ11
    v12 = zero * VJ02 + j11 * VJ12
    v20 = j02 * VJ00 + j12 * VJ10
    v21 = j02 * VJ01 + j12 * VJ11
    v22 = j02 * VJ02 + j12 * VJ12
    vJ00 = two * (VJ00 * C00 + VJ01 * C10 + VJ02 * C20)
    vJ02 = two * (VJ00 * C02 + VJ01 * C12 + VJ02 * C22)
    vJ11 = two * (VJ10 * C01 + VJ11 * C11 + VJ12 * C21)
    vJ12 = two * (VJ10 * C02 + VJ11 * C12 + VJ12 * C22)
    # v_Sigma = Rw^T vCc Rw
    a00 = w00 * v00 + w10 * v10 + w20 * v20
    a01 = w00 * v01 + w10 * v11 + w20 * v21
    a02 = w00 * v02 + w10 * v12 + w20 * v22
    a10 = w01 * v00 + w11 * v10 + w21 * v20
    a11 = w01 * v01 + w11 * v11 + w21 * v21
    a12 = w01 * v02 + w11 * v12 + w21 * v22
    a20 = w02 * v00 + w12 * v10 + w22 * v20
    a21 = w02 * v01 + w12 * v11 + w22 * v21
    a22 = w02 * v02 + w12 * v12 + w22 * v22
    S00 = a00 * w00 + a01 * w10 + a02 * w20
    S01 = a00 * w01 + a01 * w11 + a02 * w21
    S02 = a00 * w02 + a01 * w12 + a02 * w22
    S10 = a10 * w00 + a11 * w10 + a12 * w20
    S11 = a10 * w01 + a11 * w11 + a12 * w21
    S12 = a10 * w02 + a11 * w12 + a12 * w22
    S20 = a20 * w00 + a21 * w10 + a22 * w20
    S21 = a20 * w01 + a21 * w11 + a22 * w21
    S22 = a20 * w02 + a21 * w12 + a22 * w22
    tz2 = tz * tz
    v_tz = -fx / tz2 * vJ00 - fy / tz2 * vJ11
    v_tz += fx * u / tz2 * vJ02 + fy * v / tz2 * vJ12
    v_u = -fx / tz * vJ02
    v_v = -fy / tz * vJ12
    tx_u = zero + v_u / tz
    tz_u = v_tz + -v_u * t0 / tz2
    v_tx = zero if clx else tx_u
    v_tz = v_tz if clx else tz_u
    ty_v = zero + v_v / tz
    tz_v = v_tz + -v_v * t1 / tz2
    v_ty = zero if cly else ty_v
    v_tz = v_tz if cly else tz_v
    vm0, vm1 = buf[IN_VM0 * L + l], buf[IN_VM1 * L + l]
    v_tx += fx / tz * vm0
    v_ty += fy / tz * vm1
    v_tz += -fx * t0 / tz2 * vm0 - fy * t1 / tz2 * vm1
    v_tz += buf[IN_VZ * L + l]
    out[OUT_M0 * L + l] = (v_tx * w00 + v_ty * w10 + v_tz * w20) + buf[IN_VSX * L + l]
    out[OUT_M1 * L + l] = (v_tx * w01 + v_ty * w11 + v_tz * w21) + buf[IN_VSY * L + l]
    out[OUT_M2 * L + l] = (v_tx * w02 + v_ty * w12 + v_tz * w22) + buf[IN_VSZ * L + l]
    # COV-02: vM[i, j] = sum_k (vS[i, k] + vS[k, i]) M[k, j]
    e00, e01, e02 = S00 + S00, S01 + S10, S02 + S20
    e10, e11, e12 = S10 + S01, S11 + S11, S12 + S21
    e20, e21, e22 = S20 + S02, S21 + S12, S22 + S22
    vM00 = e00 * M00 + e01 * M10 + e02 * M20
    vM01 = e00 * M01 + e01 * M11 + e02 * M21
    vM02 = e00 * M02 + e01 * M12 + e02 * M22
    vM10 = e10 * M00 + e11 * M10 + e12 * M20
    vM11 = e10 * M01 + e11 * M11 + e12 * M21
    vM12 = e10 * M02 + e11 * M12 + e12 * M22
    vM20 = e20 * M00 + e21 * M10 + e22 * M20
    vM21 = e20 * M01 + e21 * M11 + e22 * M21
    vM22 = e20 * M02 + e21 * M12 + e22 * M22
    G00, G01, G02 = vM00 * S0, vM01 * S1, vM02 * S2
    G10, G11, G12 = vM10 * S0, vM11 * S1, vM12 * S2
    G20, G21, G22 = vM20 * S0, vM21 * S1, vM22 * S2
    out[OUT_LS0 * L + l] = (vM00 * R00 + vM10 * R10 + vM20 * R20) * S0
    out[OUT_LS1 * L + l] = (vM01 * R01 + vM11 * R11 + vM21 * R21) * S1
    out[OUT_LS2 * L + l] = (vM02 * R02 + vM12 * R12 + vM22 * R22) * S2
    vw = two * (-z * G01 + y * G02 + z * G10 - x * G12 - y * G20 + x * G21)
    vx = two * (y * G01 + z * G02 + y * G10 - two * x * G11
                - w * G12 + z * G20 + w * G21 - two * x * G22)
    vy = two * (-two * y * G00 + x * G01 + w * G02 + x * G10
                + z * G12 - w * G20 + z * G21 - two * y * G22)
    vz = two * (-two * z * G00 - w * G01 + x * G02 + w * G10
                - two * z * G11 + y * G12 + x * G20 + y * G21)
    dot = w * vw + x * vx + y * vy + z * vz
    out[OUT_Q0 * L + l] = (vw - w * dot) / qn
    out[OUT_Q1 * L + l] = (vx - x * dot) / qn
    out[OUT_Q2 * L + l] = (vy - y * dot) / qn
    out[OUT_Q3 * L + l] = (vz - z * dot) / qn


@njit(cache=True, inline="always", error_model="numpy")
def _max(a, b):
    """max(a, b) as the builtin gives it (a unless b > a), as a select."""
    return b if b > a else a


@njit(cache=True, inline="always", error_model="numpy")
def _min(a, b):
    """min(a, b) as the builtin gives it (a unless b < a), as a select."""
    return b if b < a else a


@njit(cache=True, inline="always", error_model="numpy")
def projection_forward_lane(buf, out, l, w2, cs, fl):
    """Lane l of a block: camera frame, depth, 2D mean, EWA covariance with dilation, conic,
    antialiasing compensation and the opacity used (COV-01, PRJ-01..PRJ-04, PRJ-08), from the
    FIN_* fields of ``buf`` into the FOUT_* fields of ``out``.  cs = (0, 1, 2, 1/2, eps2d, fx,
    fy, cx, cy, lim_x-, lim_x+, lim_y-, lim_y+, near, far) in the dtype; fl = (near inclusive,
    det <= 0 culled, antialiased) booleans.  The conic is inverted on the entries divided by
    m = max(|a|, |c|), so that nothing overflows for huge splats (HARD-11), as refgs.projection."""
    L = BLOCK
    (zero, one, two, half, eps, fx, fy, cx, cy, lnx, lpx, lny, lpy, near, far) = cs
    near_inclusive, det_nonpositive, antialiased = fl
    (w, x, y, z, qn, R00, R01, R02, R10, R11, R12, R20, R21, R22,
     M00, M01, M02, M10, M11, M12, M20, M21, M22, t0, t1, t2,
     C00, C01, C02, C10, C11, C12, C20, C21, C22) = camera_frame(
        buf[FIN_Q0 * L + l], buf[FIN_Q1 * L + l], buf[FIN_Q2 * L + l], buf[FIN_Q3 * L + l],
        buf[FIN_M0 * L + l], buf[FIN_M1 * L + l], buf[FIN_M2 * L + l], buf[FIN_S0 * L + l],
        buf[FIN_S1 * L + l], buf[FIN_S2 * L + l], w2, zero, one, two)
    tz = t2
    in_depth = ((tz > near) if near_inclusive else (tz >= near)) & (tz <= far)     # PRJ-02
    tzs = tz if in_depth else one
    out[FOUT_Z * L + l] = tz
    mx = fx * t0 / tzs + cx                                                       # CNV-08
    my = fy * t1 / tzs + cy
    out[FOUT_MX * L + l] = mx
    out[FOUT_MY * L + l] = my
    # PRJ-03: the clamped EWA Jacobian
    u = _min(_max(t0 / tzs, -lnx), lpx)
    v = _min(_max(t1 / tzs, -lny), lpy)
    j00, j02, j11, j12 = fx / tzs, -fx * u / tzs, fy / tzs, -fy * v / tzs
    # PRJ-04: J Cc J^T, symmetrised, dilated
    r00 = j00 * C00 + j02 * C20
    r01 = j00 * C01 + j02 * C21
    r02 = j00 * C02 + j02 * C22
    r10 = j11 * C10 + j12 * C20
    r11 = j11 * C11 + j12 * C21
    r12 = j11 * C12 + j12 * C22
    m00 = r00 * j00 + r02 * j02
    m01 = r01 * j11 + r02 * j12
    m10 = r10 * j00 + r12 * j02
    m11 = r11 * j11 + r12 * j12
    a = m00 + eps
    b = half * (m01 + m10)
    c = m11 + eps
    out[FOUT_A * L + l] = a
    out[FOUT_B * L + l] = b
    out[FOUT_C * L + l] = c
    m = _max(abs(a), abs(c))
    m = m if m > zero else one
    a1, b1, c1 = a / m, b / m, c / m
    det1 = a1 * c1 - b1 * b1
    det_ok = (det1 > zero) if det_nonpositive else (det1 != zero)
    det1s = det1 if det_ok else one
    md = m * det1s
    out[FOUT_K0 * L + l] = c1 / md
    out[FOUT_K1 * L + l] = -b1 / md
    out[FOUT_K2 * L + l] = a1 / md
    e1 = eps / m                                                                  # PRJ-08
    det0_1 = (a1 - e1) * (c1 - e1) - b1 * b1
    cp_aa = math.sqrt(_max(zero, det0_1 / det1s))
    cp = cp_aa if antialiased else one
    out[FOUT_CP * L + l] = cp
    out[FOUT_O * L + l] = buf[FIN_OSIG * L + l] * buf[FIN_OSCALE * L + l] * cp
    out[FOUT_A1 * L + l] = a1
    out[FOUT_C1 * L + l] = c1
    out[FOUT_DET1 * L + l] = det1
    out[FOUT_M * L + l] = m
    out[FOUT_VIS * L + l] = one if (in_depth & det_ok) else zero


@njit(cache=True, inline="always", error_model="numpy")
def _clip_tile(x, hi):
    """A tile bound as refgs.projection.tile_rectangles clips it, in selects: nan -> 0, then
    clipped to [0, hi], as int64."""
    xi = np.int64(_min(_max(x, 0.0), np.float64(hi)))       # finite after the clip (nan -> 0)
    return 0 if x != x else xi


@njit(cache=True, inline="always", error_model="numpy")
def extent_lane(out, r64, ri, l, cs, sigma64, fl, dims):
    """Lane l of a block: radius (PRJ-05), visibility and tile rectangle (RAS-01, PRF-08) from
    :func:`projection_forward_lane`'s FOUT_* fields (FOUT_EXT staged by the caller when the
    opacity cull is on) into r64 (R64_*) and ri (RI_*).  cs = (0, 1/2, eig floor, sigma, alpha
    min) in the dtype; sigma64 the radius sigma in float64; fl = (eig rule, opacity cull, inria
    tiles, offscreen cull); dims = (W, H, gx, gy).  Both radius rules are computed and one is
    selected; gsplat's extend and the rectangle are float64 (refgs.projection.tile_rectangles)."""
    L = BLOCK
    zero, half, eig_floor, sigma, amin = cs
    eig_rule, opacity_cull, inria_tiles, offscreen_cull = fl
    W, H, gx, gy = dims
    T = _TILE
    a, c = out[FOUT_A * L + l], out[FOUT_C * L + l]
    a1, c1 = out[FOUT_A1 * L + l], out[FOUT_C1 * L + l]
    det1, m = out[FOUT_DET1 * L + l], out[FOUT_M * L + l]
    o_eff = out[FOUT_O * L + l]
    vis = out[FOUT_VIS * L + l] != zero
    # eig rule (inria)
    mid1 = half * (a1 + c1)
    root = m * math.sqrt(_max(mid1 * mid1 - det1, zero))
    lam1 = m * mid1 + _max(math.sqrt(eig_floor), root)
    r_eig = np.float64(np.ceil(sigma * math.sqrt(_max(lam1, zero))))
    # gsplat rule
    ext = _min(sigma64, np.float64(out[FOUT_EXT * L + l])) if opacity_cull else sigma64
    vis_g = (vis & (o_eff >= amin)) if opacity_cull else vis
    rx_g = np.ceil(ext * np.float64(math.sqrt(_max(a, zero))))
    ry_g = np.ceil(ext * np.float64(math.sqrt(_max(c, zero))))
    vis_g = vis_g & (not ((rx_g <= 0.0) & (ry_g <= 0.0)))
    rx = r_eig if eig_rule else rx_g
    ry = r_eig if eig_rule else ry_g
    vis = vis if eig_rule else vis_g
    rx = rx if vis else 0.0
    ry = ry if vis else 0.0
    fmx, fmy = np.float64(out[FOUT_MX * L + l]), np.float64(out[FOUT_MY * L + l])
    px, py = fmx - 0.5, fmy - 0.5
    x0i = np.trunc((px - rx) / T)
    x1i = np.trunc((px + rx + T - 1.0) / T)
    y0i = np.trunc((py - ry) / T)
    y1i = np.trunc((py + ry + T - 1.0) / T)
    x0g = np.floor(fmx / T - rx / T)
    x1g = np.ceil(fmx / T + rx / T)
    y0g = np.floor(fmy / T - ry / T)
    y1g = np.ceil(fmy / T + ry / T)
    ix0 = _clip_tile(x0i if inria_tiles else x0g, gx)
    ix1 = _clip_tile(x1i if inria_tiles else x1g, gx)
    iy0 = _clip_tile(y0i if inria_tiles else y0g, gy)
    iy1 = _clip_tile(y1i if inria_tiles else y1g, gy)
    off = (fmx + rx <= 0.0) | (fmx - rx >= W) | (fmy + ry <= 0.0) | (fmy - ry >= H)
    vis = vis & (not (offscreen_cull & off))
    vis = vis & (ix1 > ix0) & (iy1 > iy0)
    r64[R64_X * L + l] = rx
    r64[R64_Y * L + l] = ry
    ri[RI_X0 * L + l] = ix0
    ri[RI_X1 * L + l] = ix1
    ri[RI_Y0 * L + l] = iy0
    ri[RI_Y1 * L + l] = iy1
    ri[RI_VIS * L + l] = 1 if vis else 0
