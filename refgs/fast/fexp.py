"""A vectorisable exp for the compositing loops of refgs.fast (float64 and float32).

Why: numba compiles ``math.exp`` to a call of the C library's scalar exp, and a loop that calls it
cannot be turned into SIMD code; the compositing kernels spend most of their time around that call
(docs/fast.md, "Speed").  :func:`fast_exp` is written only with multiplies, adds, one comparison
pair and two bit casts, so LLVM vectorises the loops it is inlined into.

Method (Cody & Waite range reduction, e.g. Muller, *Elementary Functions*, ch. 11):

    k = round(x / ln 2)  (by adding and subtracting ROUND_SHIFT = 1.5 * 2^m, m = mantissa bits),
    r = (x - k LN2_HI) - k LN2_LO,  |r| <= ln(2) / 2 (LN2_HI has trailing zero bits, so k LN2_HI
    is exact for the k used here),
    exp(x) = 2^k * P(r),  P the Taylor polynomial of degree 13 (float64) / 7 (float32)
    (evaluated by Estrin's scheme, :func:`_poly64`), whose
    truncation error |r|^(n+1) / (n+1)! is 4e-18 / 5e-9 relative -- below half an ulp,
    2^k built from the bits of (x / ln 2 + ROUND_SHIFT): its low bits are k, plus the exponent
    bias, shifted into the exponent field.

Accuracy: at most 1 ulp from the correctly rounded exp over [X_MIN, 0] (tests/test_fexp.py checks
this against numpy's exp on a million points of each dtype); ``math.exp`` itself is within 1 ulp,
so the two can differ by one ulp, never more.

Domain: the compositing kernels only use exp(power) for power <= 0 (RAS-03 skips power > 0), so
arguments are clamped to [X_MIN, 0]: below X_MIN the result is exp(X_MIN) (9.9e-305 / 1.6e-38)
instead of a smaller or zero value -- in the kernels that always gives alpha < 1/255, the same
decision as the exact value, because opacities are at most 1 -- and above 0 it is 1 (those
fragments are skipped).  NaN stays NaN.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic, overload


@intrinsic
def _f64_to_bits(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))
    return types.int64(types.float64), codegen


@intrinsic
def _bits_to_f64(typingctx, i):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


@intrinsic
def _f32_to_bits(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.int32(types.float32), codegen


@intrinsic
def _bits_to_f32(typingctx, i):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.int32), codegen


# ---- float64 constants -------------------------------------------------------------------------
#: 1 / ln 2
INV_LN2 = 1.4426950408889634
#: ln 2 split in a part with 32 trailing zero bits and the rest (fdlibm's e_exp.c values)
LN2_HI = 6.93147180369123816490e-01
LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds to an integer held in the low mantissa bits
ROUND_SHIFT = 6755399441055744.0
#: smallest argument (2^k stays a normal number: k >= -1010)
X_MIN = -700.0
_BIAS64, _MANT64 = 1023, 52
_P64 = tuple(1.0 / math.factorial(k) for k in range(14))

# ---- float32 constants -------------------------------------------------------------------------
INV_LN2_F32 = np.float32(1.4426950408889634)
#: ln 2 = 0.693359375 (9 significant bits) - 2.12194440e-4
LN2_HI_F32 = np.float32(0.693359375)
LN2_LO_F32 = np.float32(-2.12194440e-4)
#: 1.5 * 2^23
ROUND_SHIFT_F32 = np.float32(12582912.0)
#: smallest float32 argument (k >= -126)
X_MIN_F32 = np.float32(-87.0)
_BIAS32, _MANT32 = np.int32(127), np.int32(23)
_P32 = tuple(np.float32(1.0 / math.factorial(k)) for k in range(8))

_a0, _a1, _a2, _a3, _a4, _a5, _a6, _a7, _a8, _a9, _a10, _a11, _a12, _a13 = _P64
_b0, _b1, _b2, _b3, _b4, _b5, _b6, _b7 = _P32
_ZERO32 = np.float32(0.0)


@njit(inline="always", error_model="numpy")
def _poly64(r):
    """P(r) = 1 + (r + r^2 T(r)), T(r) = sum_{k=2..13} r^(k-2) / k!, T by Estrin's scheme.

    Horner's rule is a chain of 13 dependent multiply-adds; in the compositing lanes that chain's
    latency, not the arithmetic, bounds the speed.  Estrin's scheme evaluates T in independent
    pairs (a_k + a_(k+1) r) joined with r^2, r^4, r^8: about a third of the latency for three
    extra multiplies.  The two terms that set the rounding of the result, 1 and r, are added last
    (as Horner's last step does), so T's own rounding is scaled by r^2 <= 0.12 and the accuracy
    of the result is unchanged (tests/test_fexp.py)."""
    r2 = r * r
    r4 = r2 * r2
    r8 = r4 * r4
    t = ((_a2 + _a3 * r) + r2 * (_a4 + _a5 * r)) \
        + r4 * ((_a6 + _a7 * r) + r2 * (_a8 + _a9 * r)) \
        + r8 * ((_a10 + _a11 * r) + r2 * (_a12 + _a13 * r))
    return _a0 + (r + r2 * t)


@njit(inline="always", error_model="numpy")
def _poly32(r):
    """The float32 P(r) = 1 + (r + r^2 T(r)), T = sum_{k=2..7} r^(k-2) / k! by Estrin's scheme
    (:func:`_poly64`)."""
    r2 = r * r
    r4 = r2 * r2
    t = ((_b2 + _b3 * r) + r2 * (_b4 + _b5 * r)) + r4 * (_b6 + _b7 * r)
    return _b0 + (r + r2 * t)


@njit(inline="always", error_model="numpy")
def fast_exp64(x):
    """exp(x) for float64 x, clamped to [X_MIN, 0] (module docstring)."""
    x = X_MIN if x < X_MIN else x
    x = 0.0 if x > 0.0 else x
    t = x * INV_LN2 + ROUND_SHIFT
    k = t - ROUND_SHIFT
    r = (x - k * LN2_HI) - k * LN2_LO
    p = _poly64(r)
    return p * _bits_to_f64((_f64_to_bits(t) + _BIAS64) << _MANT64)


@njit(inline="always", error_model="numpy")
def fast_exp32(x):
    """exp(x) for float32 x in float32 arithmetic, clamped to [X_MIN_F32, 0]."""
    x = X_MIN_F32 if x < X_MIN_F32 else x
    x = _ZERO32 if x > _ZERO32 else x
    t = x * INV_LN2_F32 + ROUND_SHIFT_F32
    k = t - ROUND_SHIFT_F32
    r = (x - k * LN2_HI_F32) - k * LN2_LO_F32
    p = _poly32(r)
    return p * _bits_to_f32((_f32_to_bits(t) + _BIAS32) << _MANT32)


def fast_exp(x):
    """exp(x) in the dtype of x (float64 or float32), for use inside numba kernels; the Python
    fallback is numpy's exp of the clamped argument (module docstring)."""
    x = np.asarray(x)
    lo = X_MIN if x.dtype == np.float64 else X_MIN_F32
    return np.exp(np.clip(x, lo, 0).astype(x.dtype))


@overload(fast_exp, inline="always")
def _fast_exp_overload(x):
    if x == types.float64:
        return lambda x: fast_exp64(x)
    if x == types.float32:
        return lambda x: fast_exp32(x)
    return None


@njit(cache=True, error_model="numpy")
def fast_exp_array(x, out):
    """out[i] = fast_exp(x[i]) (a vectorised loop; used by the tests and the accuracy check)."""
    for i in range(x.size):
        out[i] = fast_exp(x[i])
