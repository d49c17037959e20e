"""Comparison helpers: one backend output against the float64 reference (ORC-03, ORC-04).

Every helper returns a :class:`Comparison` (never raises on a mismatch) whose ``message`` is one
sentence with fixed parts, in the array-api-tests style:

    image[12, 40, 1]=0.4121, but should be roughly 0.4133 (|diff|=1.2e-03, tol=3.0e-05)

Element bound (tolerances.Tol): ``|got - ref| <= atol' + rtol * |ref|`` where ``atol' = atol`` or,
for rows with ``scaled=True`` (gradients, covariances), ``atol * s_i`` with s_i the largest
|ref| in the element's row i (its Gaussian), floored at ``row_floor * max|ref|``.  ``ratio`` is the
worst |diff| / bound; a check passes when every ratio is <= 1.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


#: calibration hook (``python -m oracle calibrate``): when a list, every value comparison appends
#: (tolerance row, label, measurements) to it; None in normal runs
RECORDER: list | None = None


def _record(tol, label: str, **measured) -> None:
    if RECORDER is not None:
        RECORDER.append((tol, label, measured))


@dataclass
class Comparison:
    """Outcome of comparing one output (or one property) of the backend with the reference."""

    output: str
    ok: bool
    message: str = ""
    ratio: float = 0.0
    index: tuple | None = None
    got: float | None = None
    expected: float | None = None
    error: float | None = None
    bound: float | None = None
    n_compared: int = 0
    n_bad: int = 0
    ties: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    #: what sort of problem a failure is: "value" (out of tolerance, or a property that does not
    #: hold), "dtype", "shape", "missing", "nonfinite", "malformed" (not a numeric array),
    #: "exception" (the backend raised), "oracle" (the oracle could not evaluate)
    kind: str = "value"
    #: what produced the evidence: "forward", "backward", "stage", "errors", "reference"
    #: (set by oracle/evaluate.py; oracle/blame.py reads it)
    evidence: str = ""
    #: for kind "exception": the exception's type and the line it was raised at
    origin: str = ""
    #: the graded size of a failure: the sum of error / tolerance over the judged elements out
    #: of tolerance (each at most RATIO_LIMIT; exact outputs: EXACT_EXCESS per differing
    #: element); what the diagnosis' distance is made of (oracle/search.py); 0 when every
    #: element is within tolerance
    excess: float = 0.0

    def to_json(self) -> dict:
        def f(x):
            if x is None:
                return None
            x = float(x)
            return x if np.isfinite(x) else repr(x)
        return {"output": self.output, "ok": bool(self.ok), "message": self.message,
                "ratio": f(self.ratio), "index": None if self.index is None else [int(i) for i in self.index],
                "got": f(self.got), "expected": f(self.expected), "error": f(self.error),
                "bound": f(self.bound), "n_compared": int(self.n_compared), "n_bad": int(self.n_bad),
                "ties": self.ties, "metrics": {k: f(v) for k, v in self.metrics.items()},
                "kind": self.kind, "evidence": self.evidence}


#: the excess of one differing element of an exact (integer or boolean) output
EXACT_EXCESS = 1.0
#: an element's error / tolerance counts at most this much in the excess (a zero bound: inf)
RATIO_LIMIT = 1e12


def _fmt(x) -> str:
    return f"{x:.6g}" if isinstance(x, (float, np.floating)) else str(x)


def problem(output: str, message: str, kind: str = "value", origin: str = "") -> Comparison:
    """A failed comparison that is not about tolerances (a missing field, an exception, a wrong
    shape, a property that does not hold); ``kind`` as :attr:`Comparison.kind`."""
    return Comparison(output, False, message, ratio=np.inf, kind=kind, origin=origin)


def fine(output: str, message: str = "") -> Comparison:
    return Comparison(output, True, message)


def check_array(output: str, got, shape, dtype: str | None) -> Comparison | None:
    """Shape, dtype and finiteness of a backend array (API-04, API-05, CNV-11); None when fine."""
    if got is None:
        return problem(output, f"{output} is missing from the backend's result", "missing")
    if hasattr(got, "message") and not hasattr(got, "shape"):          # protocol.Malformed
        return problem(output, got.message, "malformed")
    if tuple(got.shape) != tuple(shape):
        return problem(output, f"{output}.shape={tuple(got.shape)}, but should be {tuple(shape)}",
                       "shape")
    if dtype is not None and got.dtype.kind == "f" and str(got.dtype) != dtype:
        return problem(output, f"{output}.dtype={got.dtype}, but should be {dtype} (the backend's "
                               f"declared dtype, CNV-11)", "dtype")
    if got.dtype.kind == "f" and not np.all(np.isfinite(got)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(got))[0])
        return problem(output, f"{output}{list(bad)}={got[bad]}, but should be finite", "nonfinite")
    return None


def row_scale(ref: np.ndarray, floor: float, companion=None) -> np.ndarray:
    """Per-row (leading index) scale for ``scaled`` tolerance rows, shape (R, 1, ...).

    s_i = max(max|ref[i, ...]|, companion[i]), floored at ``floor`` times the largest s_i.
    ``companion`` gives a row its natural size when its own reference value is cancellation
    noise (the quaternion gradient of an isotropic Gaussian is exactly 0 in exact arithmetic).
    """
    r = np.abs(np.asarray(ref, np.float64)).reshape(ref.shape[0], -1) if ref.ndim > 1 \
        else np.abs(np.asarray(ref, np.float64))[:, None]
    rows = r.max(axis=1) if r.size else np.zeros(ref.shape[0])
    if companion is not None:
        rows = np.maximum(rows, np.asarray(companion, np.float64))
    top = float(rows.max(initial=0.0))
    return np.maximum(rows, floor * top).reshape((-1,) + (1,) * (ref.ndim - 1))


def compare_values(output: str, got: np.ndarray, ref: np.ndarray, tol, *, select=None,
                   exempt=None, scale=None, extra=None) -> Comparison:
    """Element-wise comparison under ``tol`` (a tolerances.Tol).

    select: bool mask (broadcastable) of the elements that are compared at all (e.g. visible
    Gaussians); exempt: bool mask of near-tie elements (ORC-04): compared, but a violation there
    is counted as a *flip* and reported, not failed.  The tie budget is enforced by the caller.
    scale: per-element atol multiplier (broadcastable); default :func:`row_scale` for ``scaled``
    rows, 1 otherwise.  extra: an additive per-element allowance (broadcastable), the
    conditioning term of ORC-04.
    """
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    sel = np.ones(ref.shape, bool) if select is None else np.broadcast_to(select, ref.shape)
    ex = np.zeros(ref.shape, bool) if exempt is None else np.broadcast_to(exempt, ref.shape)
    if scale is None:
        scale = row_scale(np.where(sel, ref, 0.0), tol.row_floor) if (tol.scaled and ref.size) else 1.0
    bound = tol.atol * scale + tol.rtol * np.abs(ref)
    if extra is not None:
        bound = bound + extra
    diff = np.abs(got - ref)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(diff == 0, 0.0, diff / bound)
    bad = (ratio > 1) & sel
    if RECORDER is not None and (sel & ~ex).any():
        with np.errstate(divide="ignore", invalid="ignore"):
            need = (diff - (bound - tol.atol * scale)) / np.broadcast_to(scale, ref.shape)
        _record(tol, output, atol_needed=float(np.max(np.where(sel & ~ex, need, -np.inf))),
                flips=int((bad & ex).sum()), in_band=int((sel & ex).sum()))
    flips = bad & ex
    bad &= ~ex
    considered = np.where(sel & ~ex, ratio, -1.0)
    n_cmp = int((sel & ~ex).sum())
    ties = {"elements_in_band": int((sel & ex).sum()), "flips": int(flips.sum())} if exempt is not None else {}
    if n_cmp == 0:
        return Comparison(output, True, f"{output}: nothing to compare", ties=ties)
    idx = np.unravel_index(int(np.argmax(considered)), ref.shape)
    worst = float(considered[idx])
    excess = float(np.sum(np.minimum(ratio[bad], RATIO_LIMIT))) if bad.any() else 0.0
    c = Comparison(output, not bad.any(), ratio=worst, index=tuple(int(i) for i in idx),
                   got=float(got[idx]), expected=float(ref[idx]), error=float(diff[idx]),
                   bound=float(bound[idx]), n_compared=n_cmp, n_bad=int(bad.sum()), ties=ties,
                   excess=excess)
    c.message = (f"{output}{list(c.index)}={_fmt(c.got)}, but should be roughly {_fmt(c.expected)} "
                 f"(|diff|={c.error:.2e}, tol={c.bound:.2e}; {c.n_bad} of {n_cmp} elements out of "
                 f"tolerance)") if not c.ok else (
        f"{output}: worst |diff|={c.error:.2e} at {list(c.index)}, {worst:.3g} of its tolerance")
    return c


def compare_exact(output: str, got: np.ndarray, ref: np.ndarray, *, select=None, exempt=None) -> Comparison:
    """Integer / boolean outputs: equal everywhere outside the exempt (near-tie) elements."""
    got = np.asarray(got)
    ref = np.asarray(ref)
    sel = np.ones(ref.shape, bool) if select is None else np.broadcast_to(select, ref.shape)
    ex = np.zeros(ref.shape, bool) if exempt is None else np.broadcast_to(exempt, ref.shape)
    neq = (got != ref) & sel
    bad = neq & ~ex
    ties = {"elements_in_band": int((sel & ex).sum()), "flips": int((neq & ex).sum())} if exempt is not None else {}
    n_cmp = int((sel & ~ex).sum())
    if not bad.any():
        return Comparison(output, True, f"{output}: equal on {n_cmp} elements", n_compared=n_cmp, ties=ties)
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    return Comparison(output, False, f"{output}{list(idx)}={got[idx]}, but should be exactly {ref[idx]} "
                                     f"({int(bad.sum())} of {n_cmp} elements differ)",
                      ratio=np.inf, index=idx, got=float(got[idx]), expected=float(ref[idx]),
                      error=float(abs(float(got[idx]) - float(ref[idx]))), bound=0.0,
                      n_compared=n_cmp, n_bad=int(bad.sum()), ties=ties,
                      excess=EXACT_EXCESS * int(bad.sum()))


def gradient_metrics(got: np.ndarray, ref: np.ndarray, scale: np.ndarray, floor: float,
                     companion=None, cancel=None) -> dict:
    """Whole-tensor agreement of a gradient, relative to its natural size.

    ``scale``: the per-row scale of :func:`row_scale`; S = its broadcast to the tensor's shape,
    C = the companion sizes broadcast likewise (0 without), X = the cancellation allowance (0
    without).  rel_l2 = max(0, |g - r| - |X|) / max(|r|, |C|, floor |S|) (the allowance X is
    additive); cosine(g, r), reported as 1 when |r| is below that denominator's other terms (a
    tensor of rounding noise has no direction); mag_ratio = the worst per-row
    min(|g_i|, |r_i|) / max(|g_i|, |r_i|) over rows with max(|g_i|, |r_i|) > floor s_i (a gradient
    dropped or doubled on a few Gaussians shows here, gsplat #1011).
    """
    n = ref.shape[0]
    g = np.asarray(got, np.float64).reshape(n, -1)
    r = np.asarray(ref, np.float64).reshape(n, -1)
    S = np.broadcast_to(np.asarray(scale, np.float64).reshape(n, -1), r.shape)
    nr, ng, ns = float(np.linalg.norm(r)), float(np.linalg.norm(g)), float(np.linalg.norm(S))
    nc = 0.0 if companion is None else float(np.linalg.norm(
        np.broadcast_to(np.asarray(companion, np.float64).reshape(n, 1), r.shape)))
    nx = 0.0 if cancel is None else float(np.linalg.norm(cancel))
    noise = max(nc, floor * ns)
    den = max(nr, noise)
    # the cancellation allowance is additive: only the error beyond |X| counts
    rel_l2 = max(0.0, float(np.linalg.norm(g - r)) - nx) / den if den > 0 else 0.0
    if nr > noise and ng > 0:
        cosine = float(np.sum(g * r)) / (ng * nr)
        # a perturbation of norm |X| may turn the vector by 1 - cos <= (|X| / |r|)^2 / 2
        cosine = min(1.0, cosine + 0.5 * (nx / nr) ** 2)
    else:
        cosine = 1.0 if nr <= noise else 0.0
    rg, rr = np.linalg.norm(g, axis=1), np.linalg.norm(r, axis=1)
    srow = np.linalg.norm(S, axis=1)
    xrow = np.zeros_like(srow) if cancel is None else np.linalg.norm(
        np.asarray(cancel, np.float64).reshape(n, -1), axis=1)
    rows = np.maximum(rg, rr) > np.maximum(floor * srow, xrow)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(rows, np.minimum(rg, rr) / np.maximum(rg, rr), 1.0)
    worst_row = int(np.argmin(ratio)) if ratio.size else -1
    return {"rel_l2": rel_l2, "cosine": cosine,
            "mag_ratio": float(ratio.min()) if ratio.size else 1.0, "worst_row": worst_row}


def compare_gradient(output: str, got: np.ndarray, ref: np.ndarray, tol, companion=None,
                     cond=None, ill=None, cancel=None) -> Comparison:
    """Element bound (row-scaled atol) plus the whole-tensor limits of a tolerances.GradTol row.

    companion: optional (N,) natural row sizes (see :func:`row_scale`).  cond: optional (N,)
    relative error a row may carry from the scene's conditioning (ORC-04): adds cond_i * s_i to
    the row's element bound.  ill: optional (N,) bool, rows too ill-conditioned to judge in this
    dtype: compared for finiteness only, left out of the whole-tensor metrics, counted.
    cancel: optional per-element allowance (ref's shape) for cancellation in the sum over
    pixels (ORC-04); added to the element bound and to the whole-tensor noise level.
    """
    if ref.size == 0:
        return compare_values(output, got, ref, tol)
    scale = row_scale(ref, tol.row_floor, companion)
    extra = None if cond is None else np.asarray(cond).reshape(scale.shape) * scale
    if cancel is not None:
        extra = cancel if extra is None else extra + cancel
    sel = None if ill is None else ~np.asarray(ill).reshape((-1,) + (1,) * (ref.ndim - 1))
    c = compare_values(output, got, ref, tol, scale=scale, extra=extra, select=sel)
    keep = np.ones(ref.shape[0], bool) if ill is None else ~np.asarray(ill)
    if ill is not None:
        c.ties["ill_conditioned_rows"] = int(np.sum(ill))
    if not keep.any():
        return c
    got, ref, scale = np.asarray(got)[keep], np.asarray(ref)[keep], scale[keep]
    companion = None if companion is None else np.asarray(companion)[keep]
    cancel = None if cancel is None else np.asarray(cancel)[keep]
    m = gradient_metrics(got, ref, scale, tol.mag_floor, companion, cancel)
    c.metrics = {k: v for k, v in m.items() if k != "worst_row"}
    _record(tol, output, rel_l2=m["rel_l2"], one_minus_cosine=1 - m["cosine"], mag_ratio=m["mag_ratio"])
    fails = []
    if m["rel_l2"] > tol.max_rel_l2:
        fails.append(f"relative L2 error {m['rel_l2']:.2e} > {tol.max_rel_l2:.1e}")
    if m["cosine"] < tol.min_cosine:
        fails.append(f"cosine similarity {m['cosine']:.9f} < {tol.min_cosine}")
    if m["mag_ratio"] < tol.min_mag_ratio:
        fails.append(f"row {m['worst_row']} magnitude ratio {m['mag_ratio']:.3g} < {tol.min_mag_ratio}")
    agg = max(m["rel_l2"] / tol.max_rel_l2 if tol.max_rel_l2 > 0 else 0.0,
              (1 - m["cosine"]) / (1 - tol.min_cosine) if tol.min_cosine < 1 else 0.0)
    c.ratio = max(c.ratio, agg)
    if fails:
        prefix = c.message + "; " if c.n_bad else f"{output}: "
        c.ok = False
        c.message = prefix + "; ".join(fails)
    return c
