"""Evaluate one scene: run the backend and the float64 reference, compare (ORC-03..ORC-05).

Every evaluator returns a :class:`Verdict` -- a list of :class:`~oracle.compare.Comparison` plus
the near-tie accounting -- and never raises because the backend misbehaved: an exception from
the backend becomes a failed comparison naming it.

    forward(ctx, scene)                  render() outputs against refgs.render
    backward(ctx, scene, fields)         render_backward() against refgs.render_backward
    stage(ctx, scene, name)              one stage function against refgs' stage
    expect_value_error(ctx, scene, why)  invalid input must raise ValueError (API-03)
"""
from __future__ import annotations

import traceback
from dataclasses import dataclass, field

import numpy as np
from scipy.special import expit

import refgs
from refgs.render import resolve_profile

from . import tolerances as tl
from .compare import (Comparison, check_array, compare_exact, compare_gradient, compare_values,
                      fine, problem)
from .protocol import (BackendInfo, Case, GAUSSIAN_OUTPUTS, GRAD_FIELDS, Malformed, PIXEL_OUTPUTS,
                       get_field)
from .ties import tie_distances


@dataclass
class Context:
    """What the evaluators need: the backend and the tie bands of its dtype."""

    backend: BackendInfo
    #: when a dict, the evaluators store the reference's and the backend's arrays in it (the
    #: pictures of a failure, oracle/pictures.py); None in normal runs
    capture: dict | None = None

    @property
    def profile(self) -> str:
        return self.backend.profile

    @property
    def dtype(self) -> str:
        return self.backend.dtype

    @property
    def bands(self) -> tl.TieBand:
        return tl.TIE_BANDS[self.dtype]


@dataclass
class Verdict:
    """The outcome of one check on one scene."""

    comparisons: list = field(default_factory=list)
    ties: dict = field(default_factory=dict)
    provided: set = field(default_factory=set)
    #: why the example cannot be judged (more near-ties than the budget), or None
    inconclusive: str | None = None

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.comparisons)

    @property
    def worst(self) -> Comparison | None:
        bad = [c for c in self.comparisons if not c.ok]
        pool = bad or self.comparisons
        return max(pool, key=lambda c: c.ratio) if pool else None

    def message(self) -> str:
        bad = [c.message for c in self.comparisons if not c.ok]
        return "; ".join(bad) if bad else "ok"

    def extend(self, other: "Verdict") -> "Verdict":
        self.comparisons += other.comparisons
        self.ties.update(other.ties)
        self.provided |= other.provided
        self.inconclusive = self.inconclusive or other.inconclusive
        return self


def raised(exc: BaseException) -> tuple[str, str]:
    """(type name, ``file:line``) of an exception the backend raised (in this process or, for
    oracle.isolation.RemoteError, in the worker)."""
    if hasattr(exc, "type_name"):
        return exc.type_name, exc.where
    tb = traceback.extract_tb(exc.__traceback__)
    return type(exc).__name__, (f"{tb[-1].filename}:{tb[-1].lineno} in {tb[-1].name}" if tb else "")


def _crash(what: str, exc: BaseException) -> Comparison:
    name, where = raised(exc)
    return problem(what, f"{what} raised {name}: {exc}" + (f" at {where}" if where else ""),
                   "exception", origin=f"{name}@{where}")


def _tag(v: "Verdict", evidence: str) -> "Verdict":
    """Mark the comparisons of ``v`` that have no evidence kind yet (oracle/blame.py)."""
    for c in v.comparisons:
        c.evidence = c.evidence or evidence
    return v


def _keep(ctx: "Context", key: str, **arrays) -> None:
    if ctx.capture is not None:
        ctx.capture.setdefault(key, {}).update(arrays)


def reference(scene: Case) -> refgs.RenderOutput:
    """refgs.render in float64 on the (already rounded) scene: the reference (ORC-05)."""
    return refgs.render(scene.gaussians, scene.camera, scene.config)


def _tie_accounting(ctx, ref, which: str) -> tuple[dict, dict, Comparison | None]:
    """Tie masks of the reference, the conditioning allowances (ORC-04), and ``over``: None, or
    why the scene holds more near-ties than the budget allows (the example is then inconclusive:
    it is reported, and not judged)."""
    eps = tl.COND_MARGIN * float(np.finfo(ctx.dtype).eps)
    dist = tie_distances(ref, eps)
    masks = dist.masks(ctx.bands)
    masks["cond_pixel"] = eps * dist.cond_pixel
    masks["cond_conic"] = eps * dist.cond_conic
    masks["cond_cov2d"] = eps * dist.cond_cov2d
    masks["cond_means2d"] = eps * dist.cond_means2d
    masks["cond_depths"] = eps * dist.cond_depths
    masks["cond_colors"] = eps * dist.cond_colors
    masks["cond_pixel_colour"] = eps * dist.cond_pixel_colour
    masks["cond_grad"] = eps * dist.cond
    masks["ill"] = masks["cond_grad"] > tl.ILL_CONDITIONED
    masks["n_live"] = dist.n_live
    n_pix = int(ref.alpha.size)
    n = int(masks[which].sum())
    # the budget counts per-pixel coincidences with a threshold (raw distances); a Gaussian's
    # geometric near-tie (which can flag many pixels at once) counts once, against the Gaussian
    # budget; pixels exempted only because an ill-conditioned Gaussian makes their decisions
    # uncertain are counted and reported (pixels_in_band) but are a property of scene and dtype
    per_pixel = np.zeros_like(masks[which])
    for reason in ("alpha", "stop", "depth") + (("cap",) if which == "backward" else ()):
        per_pixel |= dist.raw(reason) <= getattr(ctx.bands, reason)
    n_pp = int(per_pixel.sum())
    n_g = int(masks["gaussians"].sum())
    budget = ctx.bands.budget(n_pix)
    g_budget = ctx.bands.gaussian_budget(len(ref.gaussians))
    info = {"pixels_in_band": n, "pixel_decisions_in_band": n_pp, "budget": budget,
            "gaussians_in_band": n_g, "gaussian_budget": g_budget, "by_reason": masks["counts"]}
    over = None
    if n_pp > budget or n_g > g_budget:
        over = (f"{n_pp} of {n_pix} pixels (budget {budget}) and {n_g} Gaussians (budget "
                f"{g_budget}) are within the {ctx.dtype} band of a threshold ({masks['counts']})")
    return masks, info, over


def _cond_extra(name: str, ref, masks):
    """Conditioning allowance of an output (ORC-04): how far the reference's rounding-sensitive
    quantities (conics) can move it in the backend's dtype; None where it does not apply."""
    if "cond_pixel" not in masks:
        return None
    cp = masks["cond_pixel"]
    if name == "alpha":
        return cp
    if name == "image":
        size = max(1.0, float(np.max(np.abs(ref.colors), initial=0.0)),
                   float(np.max(np.abs(np.asarray(ref.config.background, np.float64)))))
        return cp[..., None] * size + masks["cond_pixel_colour"]
    if name == "depth":
        return cp * max(1.0, float(np.max(np.abs(ref.depths[ref.visible]), initial=0.0)))
    if name == "conics":
        return masks["cond_conic"][:, None]
    if name == "cov2d":
        return masks["cond_cov2d"][:, None]
    if name == "means2d":
        return masks["cond_means2d"][:, None]
    if name == "depths":
        return masks["cond_depths"]
    if name == "colors":
        return masks["cond_colors"]
    return None


def compare_render(ctx: Context, ref: refgs.RenderOutput, got, masks, stage="render",
                   names=PIXEL_OUTPUTS + GAUSSIAN_OUTPUTS) -> Verdict:
    """Compare every output the backend provides with the reference (API-04, CNV-11)."""
    v = Verdict()
    n = len(ref.gaussians)
    vis = ref.visible
    for name in names:
        val = get_field(got, name)
        if val is None:
            if name in ("image", "alpha"):
                v.comparisons.append(problem(name, f"{name} is missing from the backend's render "
                                                   "output (required, API-04)", "missing"))
            continue
        v.provided.add(name)
        if isinstance(val, Malformed):
            v.comparisons.append(problem(name, val.message, "malformed"))
            continue
        refv = np.asarray(getattr(ref, name))
        if name == "radii" and val.shape == (n,):
            val = np.repeat(val[:, None], 2, axis=1)
        if name in ("radii", "n_contrib", "visible"):
            if val.shape != refv.shape:
                v.comparisons.append(problem(name, f"{name}.shape={val.shape}, but should be "
                                                   f"{refv.shape}", "shape"))
                continue
            if name == "visible":
                val = val.astype(bool)
            exempt = masks["lists"] if name == "n_contrib" else masks["gaussians"][:, None] \
                if name == "radii" else masks["gaussians"]
            v.comparisons.append(compare_exact(name, val, refv, exempt=exempt))
            continue
        bad = check_array(name, val, refv.shape, ctx.dtype)
        if bad is not None:
            v.comparisons.append(bad)
            continue
        tol = tl.lookup(stage, name, ctx.dtype)
        extra = _cond_extra(name, ref, masks)
        if name in PIXEL_OUTPUTS:
            ex = masks["forward"][..., None] if refv.ndim == 3 else masks["forward"]
            v.comparisons.append(compare_values(name, val, refv, tol, exempt=ex, extra=extra))
        else:
            sel = np.ones(n, bool) if name == "depths" else vis
            sel = sel.reshape((n,) + (1,) * (refv.ndim - 1))
            v.comparisons.append(compare_values(name, val, refv, tol, select=sel, extra=extra,
                                                exempt=masks["gaussians"].reshape(sel.shape)))
    return v


def forward(ctx: Context, scene: Case, invariants=()) -> Verdict:
    """render() outputs against the reference; ``invariants`` are extra functions
    ``(ctx, scene, ref, got) -> Comparison`` (e.g. final T >= 1e-4 for HARD-07)."""
    ref = reference(scene)
    _keep(ctx, "forward", ref=ref)
    try:
        got = ctx.backend.obj.render(scene.gaussians, scene.camera, scene.config)
    except Exception as exc:                                  # the backend's failure, reported
        return _tag(Verdict([_crash("render", exc)]), "forward")
    _keep(ctx, "forward", got=got)
    masks, info, over = _tie_accounting(ctx, ref, "forward")
    if over is not None:
        return Verdict(ties={"forward": info}, inconclusive=over)
    v = compare_render(ctx, ref, got, masks)
    v.ties = {"forward": info}
    for inv in invariants:
        v.comparisons.append(inv(ctx, scene, ref, got))
    return _tag(v, "forward")


def cotangents(scene: Case, shape_hw, dtype: str, mask=None, kinds=("image",)) -> dict:
    """Random cotangents from the scene's seed, zero on near-tie pixels, rounded to ``dtype``."""
    rng = np.random.default_rng(scene.seed)
    H, W = shape_hw
    out = {}
    for k in ("image", "alpha", "depth"):
        arr = rng.normal(size=(H, W, 3) if k == "image" else (H, W))
        if k not in kinds:
            continue
        if mask is not None:
            arr[mask] = 0.0
        out[f"v_{k}"] = arr.astype(dtype).astype(np.float64)
    return out


def backward(ctx: Context, scene: Case, fields=GRAD_FIELDS + ("means2d",), kinds=("image",),
             invariants=()) -> Verdict:
    """render_backward() against refgs.render_backward for the same random cotangents (API-05).

    ``kinds``: which cotangents to pass ("image", "alpha", "depth"); those the backend's
    render_backward does not accept are left out (and recorded as not provided).
    """
    be = ctx.backend
    ref = reference(scene)
    _keep(ctx, "forward", ref=ref)
    try:
        got = be.obj.render(scene.gaussians, scene.camera, scene.config)
    except Exception as exc:
        return _tag(Verdict([_crash("render", exc)]), "forward")
    _keep(ctx, "forward", got=got)
    masks, info, over = _tie_accounting(ctx, ref, "backward")
    use = tuple(k for k in kinds if k == "image" or f"v_{k}" in be.backward_kwargs)
    cot = cotangents(scene, ref.alpha.shape, ctx.dtype, masks["backward"], use)
    info["ill_conditioned_gaussians"] = int(masks["ill"].sum())
    v = Verdict(ties={"backward": info}, inconclusive=over)
    if over is not None:
        return v
    v.provided |= {f"cotangent:{k}" for k in use}
    ref_g = refgs.render_backward(ref, **cot)
    _keep(ctx, "backward", ref=ref_g)
    try:
        got_g = be.obj.render_backward(got, **cot)
    except Exception as exc:
        v.comparisons.append(_crash("render_backward", exc))
        return _tag(v, "backward")
    _keep(ctx, "backward", got=got_g)
    cancel = cancellation(ref, scene, ctx.dtype, masks["backward"], use, ref_g, masks["n_live"])
    for name in fields:
        val = get_field(got_g, name)
        if val is None and name == "means2d":
            continue                       # optional field (API-05)
        v.provided.add(f"grad:{name}")
        v.comparisons.append(compare_gradient_field(name, val, ref_g, scene.gaussians, ctx.dtype,
                                                    masks["cond_grad"], masks["ill"], cancel[name]))
    for inv in invariants:
        v.comparisons.append(inv(ctx, scene, ref_g, got_g))
    return _tag(v, "backward")


def compare_gradient_field(name: str, val, ref_g, gaussians, dtype: str, cond=None,
                           ill=None, cancel=None) -> Comparison:
    """One gradient field of a backend (``val``) against the reference Gradients ``ref_g``.

    Quaternion gradients scale like 1/|q| (CNV-05), so rows are compared as dL/dq * |q| (the
    gradient with respect to the direction), and each row's natural size is at least
    max|dL/dlog_scales| of the same Gaussian (both come from one dL/dSigma, COV-02): an isotropic
    Gaussian's quaternion gradient is exactly 0 and its computed value is rounding noise.
    Opacity-logit gradients get the sigmoid's rounding allowance: o = sigmoid(l) carries an
    absolute error of about eps in the working dtype (1 - o rounds to 0 for l >~ 17 in float32),
    so dL/dl = o (1 - o) dL/do may be off by ``tolerances.SIGMOID_ROUNDING`` * eps * |dL/do|.
    ``cancel`` (the field's shape) is the cancellation allowance of :func:`cancellation`.
    """
    refv = np.asarray(getattr(ref_g, name))
    bad = check_array(f"d{name}", val, refv.shape, dtype)
    if bad is not None:
        return bad
    companion = None
    label = f"d{name}"
    tol = tl.lookup("backward", name, dtype)
    if name == "quats" and refv.shape[0]:
        qn = np.linalg.norm(np.asarray(gaussians.quats, np.float64), axis=1)[:, None]
        refv = refv * qn
        val = np.asarray(val, np.float64) * qn
        companion = np.abs(np.asarray(ref_g.log_scales, np.float64)).max(axis=1)
        cancel = None if cancel is None else cancel * qn
        label = "dquats*|q|"
    if name == "opacity_logits" and refv.shape[0]:
        o = expit(np.asarray(gaussians.opacity_logits, np.float64))
        slope = o * (1 - o)
        v_o = np.where(slope > 0, np.abs(refv) / np.where(slope > 0, slope, 1.0), 0.0)
        companion = tl.SIGMOID_ROUNDING * float(np.finfo(dtype).eps) / tol.atol * v_o
    return compare_gradient(label, val, refv, tol, companion=companion, cond=cond, ill=ill,
                            cancel=cancel)


def cancellation(ref, scene: Case, dtype: str, mask, kinds, ref_g, n_live) -> dict:
    """Per-element allowance for cancellation in a gradient's sum over pixels (ORC-04).

    A gradient element is a sum over the Gaussian's n live fragments of terms t_p linear in the
    cotangent; computed in a dtype of unit roundoff eps it is off by up to ~eps sum|t_p| <=
    eps sqrt(n) sqrt(sum t_p^2).  sqrt(sum t_p^2) is the element's RMS under random unit
    cotangents, estimated from this cotangent and ``tolerances.CANCEL_DRAWS`` more (float64
    reference backwards).  Returns field -> COND_MARGIN * eps * sqrt(n) * rms.
    """
    sq = {f: np.asarray(getattr(ref_g, f), np.float64) ** 2 for f in GRAD_FIELDS + ("means2d",)}
    for k in range(1, tl.CANCEL_DRAWS + 1):
        alt = Case(scene.gaussians, scene.camera, scene.config, seed=scene.seed + 7919 * k)
        g = refgs.render_backward(ref, **cotangents(alt, ref.alpha.shape, dtype, mask, kinds))
        for f in sq:
            sq[f] += np.asarray(getattr(g, f), np.float64) ** 2
    eps = tl.COND_MARGIN * float(np.finfo(dtype).eps)
    root_n = np.sqrt(np.asarray(n_live, np.float64))
    return {f: eps * root_n.reshape((-1,) + (1,) * (v.ndim - 1)) * np.sqrt(v / (tl.CANCEL_DRAWS + 1))
            for f, v in sq.items()}


# ---------------------------------------------------------------------------------------------
# stage functions (ORC-01)
# ---------------------------------------------------------------------------------------------


def stage(ctx: Context, scene: Case, name: str) -> Verdict:
    """One optional stage function against refgs' stage, on inputs taken from the reference.

    The expected values honour the scene's profile and ``RenderConfig.deviations`` (DEV-01) in
    every stage, as :func:`reference` does; the backend's stage function gets the config as it is
    (the diagnosis, oracle/diagnose.py, strips the deviations before the backend sees it).
    """
    be = ctx.backend
    fn = be.stages[name]
    g, cam, cfg = scene.gaussians, scene.camera, scene.config
    ref = reference(scene)
    profile = resolve_profile(cfg)

    def rnd(a):
        return np.asarray(a, np.float64).astype(ctx.dtype).astype(np.float64)

    masks, info, over = _tie_accounting(ctx, ref, "forward")
    v = Verdict(ties={"forward": info}, inconclusive=over)
    if over is not None:
        return v
    try:
        if name == "covariance":
            exp = refgs.covariance_3d(g.quats, g.log_scales, profile)["cov3d"]
            got = fn(g.quats, g.log_scales)
            outs = {"cov3d": (_value(got), exp, None)}
        elif name == "projection":
            cov = rnd(refgs.covariance_3d(g.quats, g.log_scales)["cov3d"])
            opac = expit(g.opacity_logits)
            if cfg.opacity_scale is not None:
                opac = opac * np.asarray(cfg.opacity_scale)
            opac = rnd(opac)
            exp = refgs.project_gaussians(g.means, cov, opac, cam, profile, cfg.antialiased)
            got = fn(g.means, cov, opac, cam, cfg)
            outs = {k: (get_field(got, k), exp[k], exp["visible"] if k in ("means2d", "conics", "cov2d") else None)
                    for k in ("means2d", "conics", "depths", "radii", "cov2d", "visible")}
        elif name == "sh":
            deg = cfg.active_sh_degree(g.sh.shape[1])
            campos = rnd(cam.center)
            exp = refgs.eval_sh_colors(g.means, g.sh, campos, deg, profile)["colors"]
            got = fn(g.means, g.sh, campos, deg)
            outs = {"colors": (_value(got), exp, None)}
        elif name == "composite":
            g2d = {"means2d": rnd(ref.means2d), "conics": rnd(ref.conics),
                   "opacities": rnd(ref.opacities), "colors": rnd(ref.colors), "depths": rnd(ref.depths)}
            W, H = int(cam.width), int(cam.height)
            rect, ok = refgs.tile_rectangles(g2d["means2d"], ref.radii[:, 0], ref.radii[:, 1], W, H, profile)
            lists = refgs.build_tile_lists(rect, g2d["depths"], ref.visible & ok, W, H)
            exp = refgs.composite(g2d, lists, W, H, profile, np.asarray(cfg.background, np.float64))
            got = fn(g2d["means2d"], g2d["conics"], g2d["opacities"], g2d["colors"], g2d["depths"],
                     ref.radii.copy(), cam, cfg)
            outs = {k: (get_field(got, k), exp[k], None) for k in ("image", "alpha", "depth", "n_contrib")}
        else:
            raise KeyError(name)
    except Exception as exc:
        v.comparisons.append(_crash(f"stage_{name}", exc))
        return _tag(v, "stage")
    _keep(ctx, "stage", ref={k: np.asarray(e) for k, (_, e, _) in outs.items()},
          got={k: g_ for k, (g_, _, _) in outs.items() if g_ is not None})
    for out, (val, expv, sel) in outs.items():
        if val is None:
            if out in ("cov3d", "colors", "image", "alpha", "means2d", "conics", "depths", "radii"):
                v.comparisons.append(problem(out, f"stage_{name} returned no {out}", "missing"))
            continue
        v.provided.add(out)
        if isinstance(val, Malformed):
            v.comparisons.append(problem(out, val.message, "malformed"))
            continue
        expv = np.asarray(expv)
        if out == "radii" and val.shape == expv.shape[:1]:
            val = np.repeat(val[:, None], 2, axis=1)
        if out in ("radii", "visible", "n_contrib"):
            ex = masks["lists"] if out == "n_contrib" else (
                masks["gaussians"][:, None] if out == "radii" else masks["gaussians"])
            if val.shape != expv.shape:
                v.comparisons.append(problem(out, f"{out}.shape={val.shape}, but should be {expv.shape}",
                                             "shape"))
            else:
                v.comparisons.append(compare_exact(out, val.astype(expv.dtype), expv, exempt=ex))
            continue
        bad = check_array(out, val, expv.shape, ctx.dtype)
        if bad is not None:
            v.comparisons.append(bad)
            continue
        tol = tl.lookup(name, out, ctx.dtype)
        extra = _cond_extra(out, ref, masks) if name in ("projection", "composite") else None
        if out in ("image", "alpha", "depth"):
            ex = masks["forward"][..., None] if expv.ndim == 3 else masks["forward"]
            v.comparisons.append(compare_values(out, val, expv, tol, exempt=ex, extra=extra))
        else:
            s = None if sel is None else sel.reshape((-1,) + (1,) * (expv.ndim - 1))
            ex = masks["gaussians"].reshape((-1,) + (1,) * (expv.ndim - 1)) if name == "projection" else None
            v.comparisons.append(compare_values(out, val, expv, tol, select=s, exempt=ex, extra=extra))
    return _tag(v, "stage")


def _value(got):
    """A stage function's array result (None and protocol.Malformed pass through)."""
    if got is None or isinstance(got, Malformed):
        return got
    val = get_field({"x": got}, "x")
    return val


# ---------------------------------------------------------------------------------------------
# invalid input (API-03)
# ---------------------------------------------------------------------------------------------


def expect_value_error(ctx: Context, scene: Case, why: str) -> Verdict:
    """The reference and the backend must both raise ValueError on ``scene`` (API-03)."""
    v = Verdict()
    try:
        reference(scene)
        v.comparisons.append(problem("reference", f"refgs did not reject {why}: the oracle's "
                                                  "invalid-input case is wrong", "oracle"))
    except ValueError:
        pass
    try:
        ctx.backend.obj.render(scene.gaussians, scene.camera, scene.config)
    except ValueError:
        v.comparisons.append(fine("error", f"ValueError for {why}"))
        return _tag(v, "errors")
    except Exception as exc:
        name, where = raised(exc)
        v.comparisons.append(problem("error", f"render raised {name} for {why}, but should raise "
                                              f"ValueError (API-03): {exc}" + (f" at {where}" if where else "")))
        return _tag(v, "errors")
    v.comparisons.append(problem("error", f"render returned normally for {why}, but should raise "
                                          "ValueError (API-03)"))
    return _tag(v, "errors")
