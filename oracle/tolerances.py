"""The one tolerance table of the oracle (ORC-03), keyed by (stage, output, dtype).

Every row carries its numbers *and* its provenance as data: a rationale, the worst error measured
when the row was set, what was measured, and the margin applied.  Nothing else in the oracle
holds a tolerance.  The reference is always refgs in float64 on the same (dtype-rounded) inputs
(ORC-05); a row bounds the backend's deviation from it.

Element bound: ``|got - ref| <= atol' + rtol * |ref|`` with ``atol' = atol`` (absolute, in the
output's units) or, where ``scaled`` is True, ``atol * s_i`` with ``s_i`` the largest |ref| of the
element's Gaussian (row), floored at ``row_floor`` times the largest row (oracle/compare.py
``row_scale``): gradients span orders of magnitude between Gaussians, so each is judged against
its own size down to a floor below which a row is rounding noise (gsplat's helpers use one global
``1e-5 * max|ref|``, which leaves the small rows unchecked).  Quaternion gradients are compared
as dL/dq * |q| (they scale like 1/|q|: a 1e-30 quaternion has a 1e30 gradient), and a row whose
reference is cancellation noise (the quaternion gradient of an isotropic Gaussian is exactly 0)
is judged against a *companion* size, max|dL/dlog_scales| of the same Gaussian.  Gradient rows (:class:`GradTol`) add whole-tensor limits: relative
L2 error, cosine similarity and the per-row magnitude ratio (catches a gradient dropped or
doubled on a few Gaussians, which an element bound scaled by the largest entry can miss).

Near-ties (ORC-04) are *not* handled by tolerance: :data:`TIE_BANDS` says how close to a
threshold the reference must be for a decision to count as a near-tie in each dtype, and how many
such pixels a scene may have; oracle/ties.py finds them.

Calibration (``python -m oracle calibrate``): rows were set from the worst error over the
calibration run recorded in ``measured`` (an 'x' margin applied, rounded up to one significant
digit), never loosened to make a failing backend pass.  Integer and boolean outputs are exact.
"""
from __future__ import annotations

from dataclasses import dataclass

#: where the float32 rows were measured: refgs at float32 against refgs at float64, every check's
#: scene families, 150 examples per check, seed 0 (``python -m oracle calibrate``), both profiles;
#: the torch float32 transcription (oracle.adapters.torch_backend) measured the same way
CALIBRATION_RUN = ("python -m oracle calibrate --seed 0 with --backend "
                   "oracle.adapters.refgs_backend:refgs_float32 and :refgs_gsplat_float32 "
                   "(--max-examples 100) and oracle.adapters.torch_backend:torch_float32 (30); "
                   "worst over all checks, beyond rtol and the ORC-04 allowances")
#: the margin applied to measured worst errors
MARGIN = 4.0
#: conditioning allowance (ORC-04), in units of eps(dtype) times the reference's sensitivity
#: (oracle/ties.py ``_conditioning``): a needle's thin axis cannot be represented next to its long
#: axis better than eps * s_long^2, whatever the implementation; 4 = the calibration margin
COND_MARGIN = 4.0
#: extra float64 reference backwards (random cotangents) used to estimate each gradient element's
#: RMS for the cancellation allowance (oracle/evaluate.py ``cancellation``)
CANCEL_DRAWS = 2
#: a Gaussian whose gradient conditioning allowance COND_MARGIN * eps * cond^2 exceeds this is
#: too ill-conditioned for its gradient to be judged in that dtype: its gradient rows are checked
#: for finiteness only and counted in the report (float32: cond >~ 150, e.g. a needle of aspect
#: ~20 seen side-on; float64: cond >~ 5e6)
ILL_CONDITIONED = 0.01
#: allowance for dL/dlogit, in units of eps(dtype) * |dL/do|: sigmoid(l) is computed with an
#: absolute error of ~1 eps (1 - sigmoid(l) rounds to 0 for l >~ 17 in float32, so a float32
#: o (1 - o) is 0 where the float64 one is 4e-8); 4 = the calibration margin
SIGMOID_ROUNDING = 4.0


@dataclass(frozen=True)
class Tol:
    """One row of the table (see the module docstring for the bound)."""

    rtol: float
    atol: float
    rationale: str
    scaled: bool = False
    exact: bool = False
    row_floor: float = 0.0             # with scaled: per-row scale floored at row_floor * largest row
    measured: float | None = None      # worst atol-equivalent error seen in calibration
    measured_by: str = ""


@dataclass(frozen=True)
class GradTol(Tol):
    """A gradient row: element bound (scaled atol) plus whole-tensor limits."""

    max_rel_l2: float = 0.0
    min_cosine: float = 1.0
    min_mag_ratio: float = 0.0
    #: rows (and whole tensors) below this fraction of their natural size (row scale) are rounding
    #: noise: not ratio-checked, no cosine, rel-L2 taken against this fraction of the size
    mag_floor: float = 0.05
    measured_rel_l2: float | None = None


@dataclass(frozen=True)
class TieBand:
    """How close (relative) to a threshold the float64 reference must be for a decision to be a
    near-tie in a backend of this dtype, and how many near-tie pixels a scene may hold."""

    alpha: float      # |alpha / (1/255) - 1|                  (RAS-04)
    stop: float       # |T (1 - alpha) / 1e-4 - 1|             (RAS-05, PRF-06)
    depth: float      # |z_i - z_j| / |z| of overlapping fragments (RAS-02)
    geom: float       # relative perturbation of mean / radius / depth flipping coverage (PRJ-02, PRJ-05, PRF-08); also the frustum-clamp kink
    cap: float        # |o G / cap - 1|, gradient only          (RAS-10)
    sh: float         # |rgb| / (sum of |terms| + 0.5), gradient only (CNV-10)
    max_fraction: float
    min_allowed: int
    rationale: str

    def budget(self, n_pixels: int) -> int:
        """Most pixels with a per-pixel near-tie (alpha, stop, depth, cap) a scene of
        ``n_pixels`` may have before the check fails."""
        return max(self.min_allowed, int(self.max_fraction * n_pixels))

    def gaussian_budget(self, n: int) -> int:
        """Most Gaussians with a geometric near-tie (coverage, visibility, radius) in a scene."""
        return max(2, int(0.1 * n))


_EXACT = "integer/boolean decision: equal outside near-ties (ORC-04); near-tie elements are counted"
_F64 = ("float64 backends differ from refgs only by reassociation of sums and different but "
        "correct formula orderings: ~1e3 roundings of 1.1e-16 relative, well under 1e-10")
_F64_GRAD = ("float64 gradients by another derivation (autograd, fused kernels) agree to ~1e-12 "
             "relative for round Gaussians and 3.5e-9 for needles (measured); rel L2 2e-8 = 4x that")


#: where the float64 rows were checked: the torch transcription (autograd) against refgs
CALIBRATION_RUN_F64 = ("python -m oracle calibrate --seed 0 --max-examples 30 --backend "
                       "oracle.adapters.torch_backend:torch_float64; forward: nothing beyond rtol and "
                       "the allowances; gradients: relative L2 <= 3.5e-9 (hard_02 needles), "
                       "1 - cosine <= 6e-16")


def _f64(rtol=1e-9, atol=1e-10, why=_F64, scaled=False):
    return Tol(rtol, atol, why, scaled=scaled, measured=0.0, measured_by=CALIBRATION_RUN_F64)


def _g64(why=_F64_GRAD):
    return GradTol(1e-7, 1e-8, why, scaled=True, row_floor=1e-3, max_rel_l2=2e-8, min_cosine=1 - 1e-12,
                   min_mag_ratio=0.999, measured=0.0, measured_by=CALIBRATION_RUN_F64,
                   measured_rel_l2=3.5e-9)


#: The table.  Keys: (stage, output, dtype); stage "render" = end-to-end outputs of render(),
#: "backward" = fields of render_backward(), the others = per-stage functions (ORC-01).
TABLE: dict[tuple[str, str, str], Tol] = {}


def _put(stage, output, dtype, tol):
    TABLE[(stage, output, dtype)] = tol


# ---- exact rows (both dtypes) ---------------------------------------------------------------
for _dt in ("float32", "float64"):
    for _out in ("radii", "n_contrib", "visible"):
        for _stage in ("render", "projection", "composite"):
            _put(_stage, _out, _dt, Tol(0.0, 0.0, _EXACT, exact=True))

# ---- float64 rows ----------------------------------------------------------------------------
for _out in ("image", "alpha", "depth", "means2d", "depths", "conics", "colors", "opacities"):
    _put("render", _out, "float64", _f64())
for _out in ("means2d", "depths", "conics", "cov2d"):
    _put("projection", _out, "float64", _f64())
_put("covariance", "cov3d", "float64", _f64(atol=1e-12, scaled=True))
_put("sh", "colors", "float64", _f64())
for _out in ("image", "alpha", "depth"):
    _put("composite", _out, "float64", _f64())
for _out in ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d"):
    _put("backward", _out, "float64", _g64())

# ---- float32 rows (measured; see CALIBRATION_RUN) ----------------------------------------------
_F32 = "float32 roundings (eps 6e-8) through the stage; measured worst x{m}".format(m=MARGIN)


def _f32(rtol, atol, measured, why=_F32, scaled=False):
    return Tol(rtol, atol, why, scaled=scaled, measured=measured, measured_by=CALIBRATION_RUN)


def _g32(rtol, atol, rel_l2, measured, measured_l2, cos=1 - 1e-7, mag=0.98, why=""):
    return GradTol(rtol, atol, why or ("float32 gradients: per-pixel sums of products, 1/(1-alpha) "
                                      "amplification up to 100 (inria) / 1000 (gsplat); measured worst x"
                                      f"{MARGIN}; 1 - cosine measured <= 2.1e-8 (torch_float32, "
                                      "opaque stacks), magnitude ratio >= 0.996"), scaled=True,
                   row_floor=1e-3,
                   max_rel_l2=rel_l2, min_cosine=cos, min_mag_ratio=mag, measured=measured,
                   measured_by=CALIBRATION_RUN, measured_rel_l2=measured_l2)


# measured = worst atol the row needed (beyond rtol |ref| and the ORC-04 allowances); atol =
# MARGIN x measured rounded up to one digit, with a floor of ~2 eps of the output's size where
# nothing at all was left to measure ("floor").
_FLOOR = "measured 0 beyond rtol and the allowances; atol is a floor of ~2 eps"
_put("render", "image", "float32", _f32(1e-6, 4e-7, 9.5e-8))
_put("render", "alpha", "float32", _f32(1e-6, 1e-7, 0.0, why=_FLOOR))
_put("render", "depth", "float32", _f32(1e-6, 1e-7, 0.0, why=_FLOOR))
_put("render", "means2d", "float32", _f32(1e-7, 1e-6, 0.0, why=_FLOOR + " (pixels)"))
_put("render", "depths", "float32", _f32(1e-7, 1e-7, 0.0, why=_FLOOR))
_put("render", "conics", "float32", _f32(1e-6, 1e-7, 0.0, why=_FLOOR))
_put("render", "colors", "float32", _f32(1e-6, 4e-7, 9.4e-8))
_put("render", "opacities", "float32", _f32(1e-6, 4e-6, 9.6e-7,
                                            why=_F32 + " (gsplat's antialiasing compensation)"))
for _out in ("means2d", "depths", "conics"):
    _put("projection", _out, "float32", TABLE[("render", _out, "float32")])
_put("projection", "cov2d", "float32", _f32(1e-6, 4e-7, 6.1e-8))
_put("covariance", "cov3d", "float32", _f32(1e-6, 1e-6, 2.4e-7, scaled=True))
_put("sh", "colors", "float32", TABLE[("render", "colors", "float32")])
for _out in ("image", "alpha", "depth"):
    _put("composite", _out, "float32", TABLE[("render", _out, "float32")])
# gradients: atol is per Gaussian (row-scaled); (atol, measured atol, rel_l2, measured rel_l2)
for _out, (_a, _ma, _l2, _ml2) in {
        "means": (2e-4, 4.3e-5, 6e-5, 1.4e-5),          # worst: hard_06 (tiny scales); hard_11
        "log_scales": (2e-4, 4.8e-5, 2e-4, 4.5e-5),     # hard_06; backward_dtype
        "quats": (2e-5, 3.2e-6, 2e-4, 3.4e-5),          # hard_11 (huge splats)
        "opacity_logits": (3e-3, 5.5e-4, 5e-4, 1.2e-4),  # hard_09 (opacity 0.01); hard_07 (stacks)
        "sh": (8e-6, 1.9e-6, 5e-5, 1.2e-5),             # hard_09; hard_11
        "means2d": (8e-5, 1.8e-5, 7e-5, 1.7e-5)}.items():  # hard_06; hard_11
    _put("backward", _out, "float32", _g32(1e-6, _a, _l2, _ma, _ml2))

#: near-tie bands per backend dtype (ORC-04)
TIE_BANDS: dict[str, TieBand] = {
    "float64": TieBand(alpha=1e-9, stop=1e-9, depth=1e-12, geom=1e-12, cap=1e-9, sh=1e-12,
                       max_fraction=0.002, min_allowed=4,
                       rationale="float64 decisions flip only within ~1e3 ulp of the threshold; "
                                 "no flip met in calibration (torch_float64)"),
    "float32": TieBand(alpha=1e-4, stop=1e-3, depth=1e-5, geom=1e-5, cap=1e-4, sh=1e-5,
                       max_fraction=0.02, min_allowed=16,
                       rationale="set from the relative float32 error of each decision's inputs "
                                 "(alpha ~1e-5 near 1/255; T after tens of factors ~1e-4; "
                                 "positions and depths ~1e-6) with a 10x margin, and confirmed by "
                                 "calibration: every flip met (refgs_float32 inria 87 pixels, "
                                 "torch_float32 77) lay inside its band, none outside"),
}


def lookup(stage: str, output: str, dtype: str) -> Tol:
    """The row for (stage, output, dtype); KeyError names the missing key (a bug in the oracle)."""
    try:
        return TABLE[(stage, output, dtype)]
    except KeyError:
        raise KeyError(f"oracle/tolerances.py has no row for {(stage, output, dtype)}") from None


def rows() -> list[dict]:
    """The table as JSON-ready dicts (docs, reports, calibration output)."""
    out = []
    for (stage, output, dtype), t in sorted(TABLE.items()):
        d = {"stage": stage, "output": output, "dtype": dtype, "rtol": t.rtol, "atol": t.atol,
             "scaled": t.scaled, "exact": t.exact, "measured": t.measured,
             "measured_by": t.measured_by, "rationale": t.rationale}
        if isinstance(t, GradTol):
            d.update(max_rel_l2=t.max_rel_l2, min_cosine=t.min_cosine,
                     min_mag_ratio=t.min_mag_ratio, measured_rel_l2=t.measured_rel_l2)
        out.append(d)
    return out


def _g(x) -> str:
    return "–" if x is None else f"{x:.2g}"


def markdown_table() -> str:
    """The table as Markdown (docs/oracle.md embeds exactly this; ``python -m oracle tolerances``).

    One row per (stage, output, dtype); the near-tie bands follow as a second table.
    """
    lines = ["| stage | output | dtype | rtol | atol | scaled | rel L2 | cosine | mag ratio "
             "| measured atol | measured rel L2 | rationale |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows():
        if r["exact"]:
            bound = ("exact", "exact")
        else:
            bound = (_g(r["rtol"]), _g(r["atol"]))
        grad = (_g(r.get("max_rel_l2")), f"{r['min_cosine']:.12g}" if "min_cosine" in r else "–",
                _g(r.get("min_mag_ratio"))) if "max_rel_l2" in r else ("–", "–", "–")
        lines.append(f"| {r['stage']} | {r['output']} | {r['dtype']} | {bound[0]} | {bound[1]} "
                     f"| {'per Gaussian' if r['scaled'] else 'absolute'} | {grad[0]} | {grad[1]} "
                     f"| {grad[2]} | {_g(r['measured'])} | {_g(r.get('measured_rel_l2'))} "
                     f"| {r['rationale']} |")
    lines += ["", "Near-tie bands (ORC-04), relative distance of the float64 reference to each "
              "threshold within which a decision counts as a near-tie:", "",
              "| dtype | alpha 1/255 | T stop | depth order | geometry | cap | SH clamp "
              "| max fraction of pixels | at least | rationale |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for dt, b in sorted(TIE_BANDS.items()):
        lines.append(f"| {dt} | {b.alpha:.0e} | {b.stop:.0e} | {b.depth:.0e} | {b.geom:.0e} "
                     f"| {b.cap:.0e} | {b.sh:.0e} | {b.max_fraction:g} | {b.min_allowed} "
                     f"| {b.rationale} |")
    return "\n".join(lines) + "\n"
