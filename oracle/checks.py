"""The catalogue of checks: what is run against a backend, and which clause each one tests.

A :class:`Check` names the clauses it cites (the first is the one it is designed for), the
cases it draws (a hypothesis strategy built for the backend's declared capabilities), how one
case is evaluated (oracle/evaluate.py), and what it needs from the backend.  Status of a check
(ORC-02, ORC-11): ``pass``, ``fail``, ``error`` (the backend raised, or returned something
malformed), ``crash`` (its worker died), ``timeout``, ``known`` (a declared known difference),
``not provided`` (it needs an optional function the backend does not have: render_backward, a
stage function, an optional output), ``n/a`` (outside the backend's declared capabilities:
antialiasing, opacity_scale, SH degree, camera model, principal point, background, the other
profile).

``reference-only`` checks (kind "reference") test a property of refgs itself that no backend
interface can show (RAS-09's chunking); they run refgs, not the backend, and say so.

    CHECKS               list of every Check, in report order
    checks_for(clauses)  the checks citing any of the given ids
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable
from unittest import mock

import numpy as np
from hypothesis import strategies as st

import refgs
import refgs.rasterize
from refgs.constants import T_MIN

from . import evaluate as ev
from . import strategies as ss
from .compare import fine, problem
from .evaluate import Context, Verdict
from .hard_cases import HARD_CASES, hard_case_strategy
from .protocol import Case


@dataclass(frozen=True)
class Check:
    """One conformance check.

    name      identifier (``forward_pixel_centres``); clauses: ids it cites, designed-for first;
    kind      "forward" | "backward" | "stage" | "errors" | "hard" | "reference";
    scenes    ctx -> hypothesis strategy of Cases; evaluate: (ctx, case) -> Verdict;
    needs     capability names (see :meth:`unavailable`); examples: fraction of --max-examples;
    clause_outputs  clause -> outputs that carry its evidence (if the backend provides none of
              them, that clause is "not provided" by this check although the check ran).
    """

    name: str
    clauses: tuple
    doc: str
    kind: str
    scenes: Callable
    evaluate: Callable
    needs: tuple = ()
    examples: float = 1.0
    clause_outputs: dict = field(default_factory=dict)

    def unavailable(self, ctx: Context) -> tuple[str, str] | None:
        """("n/a" | "not provided", reason) when the check cannot run on this backend, else None."""
        be = ctx.backend
        if be.unavailable_reason and self.kind in ("forward", "backward", "errors", "hard"):
            return "n/a", f"render is unavailable here: {be.unavailable_reason}"
        for need in self.needs:
            if need == "backward" and not be.has_backward:
                return "not provided", "the backend has no render_backward"
            if need.startswith("stage:") and need[6:] not in be.stages:
                return "not provided", f"the backend has no stage_{need[6:]}"
            if need == "antialiased" and not be.supports_antialiased:
                return "n/a", "antialiased rendering is outside the backend's capabilities (gsplat only)"
            if need == "opacity_scale" and not be.supports_opacity_scale:
                return "n/a", "RenderConfig.opacity_scale is outside the backend's capabilities"
            if need == "sh>=1" and be.max_sh_degree < 1:
                return "n/a", "the backend renders SH degree 0 only"
            if need == "background" and not be.supports_background:
                return "n/a", "a background colour is outside the backend's capabilities"
            if need == "principal_point" and not be.supports_principal_point:
                return "n/a", "an off-centre principal point is outside the backend's capabilities"
            if need == "intrinsics" and not be.supports_principal_point \
                    and be.camera_model == "simple_pinhole":
                return "n/a", ("an off-centre principal point and fx != fy are outside the backend's "
                               "capabilities (camera model simple_pinhole)")
            if need.startswith("profile:") and be.profile != need[8:]:
                return "n/a", f"only for the {need[8:]} profile"
        return None


def _caps(ctx) -> ss.Capabilities:
    return ss.Capabilities.of(ctx.backend)


def _cases(**kw):
    """A cases() factory for the backend's declared capabilities."""
    def make(ctx):
        return ss.cases(_caps(ctx), **kw)
    return make


def _front(**kw):
    return lambda cam: ss.in_front_of(cam, **kw)


def _fwd(ctx, scene):
    return ev.forward(ctx, scene)


def _bwd(fields=None, kinds=("image",)):
    def run(ctx, scene):
        f = fields or ev.GRAD_FIELDS + ("means2d",)
        return ev.backward(ctx, scene, fields=f, kinds=kinds)
    return run


def _fwd_bwd(invariants=(), bwd_invariants=(), kinds=("image",)):
    """Forward, then (if the backend has one) backward on the same scene (hard cases)."""
    def run(ctx, scene):
        v = ev.forward(ctx, scene, invariants=invariants)
        if ctx.backend.has_backward and v.ok:
            v.extend(ev.backward(ctx, scene, kinds=kinds, invariants=bwd_invariants))
        return v
    return run


# ---- invariants (extra properties a check asserts besides agreement) ------------------------


def final_T_floor(ctx, scene, ref, got):
    """RAS-05 / HARD-07: the saturating fragment is not blended, so 1 - alpha >= 1e-4
    (strictly for gsplat), up to one rounding of 1 - T in the backend's dtype."""
    alpha = ev.get_field(got, "alpha")
    if alpha is None:
        return problem("final_T", "alpha missing")
    eps = float(np.finfo(ctx.dtype).eps)
    worst = float(np.max(alpha)) if alpha.size else 0.0
    limit = 1 - T_MIN + eps
    if worst > limit:
        idx = tuple(int(i) for i in np.unravel_index(int(np.argmax(alpha)), alpha.shape))
        return problem("final_T", f"alpha{list(idx)}={worst:.9g}, but should be <= 1 - 1e-4 (+1 ulp): "
                                  "the fragment that drops T below 1e-4 must not be blended (RAS-05)")
    return fine("final_T", f"max alpha {worst:.9g} <= 1 - 1e-4")


def background_exact(ctx, scene, ref, got):
    """API-06 / HARD-12: with nothing blended the image is the background exactly, alpha 0."""
    img, alpha = ev.get_field(got, "image"), ev.get_field(got, "alpha")
    if img is None or alpha is None:
        return problem("background", "image/alpha missing")
    if np.any(ref.alpha != 0):
        return fine("background", "some Gaussian is visible; not an empty scene")
    bg = np.asarray(scene.config.background, np.float64).astype(ctx.dtype)
    if not (np.all(img == bg) and np.all(alpha == 0)):
        bad = np.argwhere(np.any(img != bg, axis=-1) | (alpha != 0))
        i = tuple(int(x) for x in bad[0]) if bad.size else (0, 0)
        return problem("background", f"image{list(i)}={img[i]}, alpha={alpha[i]}, but should be "
                                     f"exactly the background {bg} and 0 (API-06)")
    return fine("background", "image == background, alpha == 0 exactly")


def grads_zero_beyond_degree(ctx, scene, ref_g, got_g):
    """SH-01 / SH-04: coefficients above the active degree receive exactly zero gradient."""
    sh = ev.get_field(got_g, "sh")
    deg = scene.config.active_sh_degree(scene.gaussians.sh.shape[1])
    nb = (deg + 1) ** 2
    if sh is None:
        return problem("dsh", "missing")
    extra = sh[:, nb:, :]
    if extra.size and np.any(extra != 0):
        i = tuple(int(x) for x in np.argwhere(extra != 0)[0])
        return problem("dsh", f"dsh[{i[0]}, {i[1] + nb}, {i[2]}]={extra[i]:.3g}, but should be exactly 0: "
                              f"coefficient {i[1] + nb} is above the active degree {deg} (SH-01, SH-04)")
    return fine("dsh", f"zero above degree {deg}")


# ---- scene families -----------------------------------------------------------------------------


def _tiny_quats(ctx):
    return ss.cases(_caps(ctx),
                    gaussians=lambda cam: ss.in_front_of(cam, n=(1, 20)).flatmap(ss.near_degenerate_quaternions),
                    label="near_degenerate_quaternions")


def _zero_quat_scene(ctx):
    return ss.cases(_caps(ctx), gaussians=_front(n=(1, 8)), label="zero quaternion").flatmap(
        lambda s: st.integers(0, max(0, s.n - 1)).map(lambda i: _zero_row(s, i)))


def _zero_row(scene: Case, i: int) -> Case:
    q = scene.gaussians.quats.copy()
    q[i] = 0.0
    return scene.with_gaussians(scene.gaussians.replace(quats=q))


#: invalid inputs of API-03 (name -> scene transform); each must raise ValueError
INVALID = {
    "a NaN mean": lambda s: s.with_gaussians(s.gaussians.replace(
        means=np.where(np.arange(s.n)[:, None] == 0, np.nan, s.gaussians.means))),
    "log_scales of shape (N, 2)": lambda s: s.with_gaussians(s.gaussians.replace(
        log_scales=s.gaussians.log_scales[:, :2])),
    "opacity_logits with N+1 rows": lambda s: s.with_gaussians(s.gaussians.replace(
        opacity_logits=np.append(s.gaussians.opacity_logits, 0.0))),
    "a non-rigid world_to_camera (scale 2)": lambda s: s.with_camera(refgs.Camera(
        np.diag([2.0, 2.0, 2.0, 1.0]) @ s.camera.world_to_camera, s.camera.K, s.camera.width, s.camera.height)),
    "fx = 0": lambda s: s.with_camera(refgs.Camera(
        s.camera.world_to_camera, np.asarray(s.camera.K) * [[0.0], [1.0], [1.0]],
        s.camera.width, s.camera.height)),
}


def _invalid_scene(ctx):
    return ss.cases(_caps(ctx), gaussians=_front(n=(1, 6)), label="invalid input").flatmap(
        lambda s: st.sampled_from(sorted(INVALID)).map(lambda k: Case(
            INVALID[k](s).gaussians, INVALID[k](s).camera, s.config, s.seed, k)))


def _invalid_eval(ctx, scene):
    return ev.expect_value_error(ctx, scene, scene.label)


def _zero_quat_eval(ctx, scene):
    return ev.expect_value_error(ctx, scene, "a zero quaternion (CNV-05)")


def _chunking_eval(ctx, scene):
    """RAS-09 (reference-only): refgs with a tiny chunk (2 list slots per segment) must make the
    same decisions and, up to reassociation, the same sums as with the default chunk."""
    ref = ev.reference(scene)
    cot = ev.cotangents(scene, ref.alpha.shape, "float64")
    g_ref = refgs.render_backward(ref, **cot)
    with mock.patch.object(refgs.rasterize, "CHUNK_PAIRS", 2 * refgs.rasterize.PIX):
        small = ev.reference(scene)
        g_small = refgs.render_backward(small, **cot)
    tol = ev.tl.lookup("render", "image", "float64")
    v = Verdict()
    v.comparisons.append(ev.compare_exact("n_contrib", small.n_contrib, ref.n_contrib))
    v.comparisons.append(ev.compare_exact("final_T", small.final_T, ref.final_T))
    v.comparisons.append(ev.compare_values("image", small.image, ref.image, tol))
    for f in ev.GRAD_FIELDS:
        v.comparisons.append(ev.compare_gradient_field(f, getattr(g_small, f), g_ref,
                                                       scene.gaussians, "float64"))
    for c in v.comparisons:
        c.evidence = "reference"
    return v


def _opaque(ctx):
    return ss.cases(_caps(ctx), gaussians=lambda c: ss.opaque_stack(c), label="opaque_stack")


def _transmittance_eval(ctx, scene):
    return ev.forward(ctx, scene, invariants=(final_T_floor,))


def _sh_bwd(ctx, scene):
    return ev.backward(ctx, scene, fields=("sh", "means"), invariants=(grads_zero_beyond_degree,))


def _empty_or_culled(ctx):
    return st.integers(0, 2**32 - 1).map(
        lambda s: HARD_CASES["HARD-12"].build(np.random.default_rng(s), _caps(ctx)))


def _empty_eval(ctx, scene):
    v = ev.forward(ctx, scene, invariants=(background_exact,))
    if ctx.backend.has_backward and v.ok:
        v.extend(ev.backward(ctx, scene))
    return v


def _hard_check(cid: str) -> Check:
    extra = {"HARD-07": (final_T_floor,), "HARD-12": (background_exact,)}.get(cid, ())
    kinds = ("image", "alpha", "depth") if cid == "HARD-10" else ("image",)
    cites = {"HARD-01": ("PRJ-07",), "HARD-02": ("PRJ-03",), "HARD-03": ("RAS-08",),
             "HARD-04": ("API-05",), "HARD-05": ("CNV-03",), "HARD-06": ("CNV-05",),
             "HARD-07": ("RAS-05",), "HARD-08": ("RAS-06",), "HARD-09": ("RAS-04",),
             "HARD-10": ("RAS-07",), "HARD-11": ("RAS-01",), "HARD-12": ("API-06",),
             "HARD-13": ("PRJ-04",)}[cid]
    needs = {"HARD-05": ("principal_point",), "HARD-10": ("background",)}.get(cid, ())
    return Check(f"hard_{cid[5:]}", (cid,) + cites, HARD_CASES[cid].doc, "hard",
                 lambda ctx, c=cid: hard_case_strategy(c, _caps(ctx)),
                 _fwd_bwd(invariants=extra, kinds=kinds), needs=needs, examples=0.5)


CHECKS: list[Check] = [
    # ---- forward, end to end ----------------------------------------------------------------
    Check("forward_generic", ("RAS-06", "API-01", "API-04", "CNV-01", "CNV-02", "PRJ-01", "RAS-03", "PRJ-06"),
          "random scenes seen from random poses: every output the backend provides", "forward",
          _cases(label="generic"), _fwd, clause_outputs={"PRJ-06": ("depth", "depths")}),
    Check("forward_dtype", ("CNV-11",), "every float output is in the backend's declared dtype",
          "forward", _cases(gaussians=_front(n=(1, 10)), label="dtype"), _fwd),
    Check("forward_intrinsics", ("CNV-03", "CNV-08", "PRF-02"),
          "off-centre principal point and fx != fy", "forward",
          _cases(camera=dict(off_centre=True, anisotropic=True), label="intrinsics"), _fwd,
          needs=("intrinsics",)),
    Check("forward_pixel_centres", ("CNV-08",),
          "sub-pixel Gaussians (dilation-sized) at random sub-pixel positions", "forward",
          _cases(gaussians=_front(scales=ss.log_scales(-9.0, -6.0), logits=(1.0, 6.0), u=(0.05, 0.95),
                                  v=(0.05, 0.95)), label="pixel_centres"), _fwd),
    Check("forward_rotations", ("CNV-04", "COV-01", "CNV-06"),
          "needle-like anisotropic Gaussians with random rotations", "forward",
          _cases(gaussians=_front(scales=ss.needle_scales(), n=(1, 20)), label="needles"), _fwd),
    Check("forward_quaternion_norms", ("CNV-05",),
          "quaternions with norms 1e-30 .. 1e3 render as their unit direction", "forward",
          _tiny_quats, _fwd),
    Check("forward_near_plane", ("PRJ-02", "PRF-01"),
          "depths straddling the profile's near plane", "forward",
          lambda ctx: ss.cases(_caps(ctx), label="straddling_near_plane",
                               gaussians=lambda c: ss.straddling_near_plane(c, ctx.profile)), _fwd),
    Check("forward_frustum_clamp", ("PRJ-03", "PRF-02"),
          "means far outside the frustum with tails reaching the image", "forward",
          lambda ctx: ss.cases(_caps(ctx), label="off_screen",
                               gaussians=lambda c: ss.off_screen(c)), _fwd),
    Check("forward_dilation", ("PRJ-04", "PRF-03"),
          "tiny scales: the 0.3 px^2 dilation decides the footprint", "forward",
          _cases(gaussians=_front(scales=ss.tiny_scales(), logits=(0.0, 6.0)), label="tiny_scales"), _fwd),
    Check("forward_coverage", ("PRJ-05", "RAS-01", "PRF-04", "PRF-08"),
          "opaque medium and huge splats: radius and tile rules decide what pixels see", "forward",
          _cases(gaussians=_front(scales=ss.either(ss.log_scales(-2.5, -0.5), ss.huge_scales()),
                                  logits=(0.0, 6.0), n=(1, 16)), label="coverage"), _fwd),
    Check("forward_depth_order", ("RAS-02",),
          "overlapping Gaussians on exactly equal depth layers: ties go by index", "forward",
          lambda ctx: ss.cases(_caps(ctx), label="depth_ties",
                               camera=dict(axis_aligned=True),
                                gaussians=lambda c: ss.depth_ties(c)), _fwd),
    Check("forward_alpha_skip", ("RAS-04", "PRF-05"),
          "faint large splats near 1/255 and saturating ones at the cap", "forward",
          _cases(gaussians=_front(logits=(-6.0, 12.0), scales=ss.log_scales(-2.0, 0.0), n=(1, 20)),
                 label="alpha_range"), _fwd),
    Check("forward_transmittance", ("RAS-05", "PRF-06"),
          "opaque stacks: T falls below 1e-4, the saturating fragment is not blended", "forward",
          _opaque, _transmittance_eval),
    Check("forward_background", ("RAS-06", "API-02"), "random background colours", "forward",
          _cases(background=True, label="background"), _fwd, needs=("background",)),
    Check("forward_sh", ("SH-02", "CNV-09", "SH-01", "SH-03"),
          "view-dependent colour: SH degree 1..max, K larger than the degree needs", "forward",
          _cases(sh_degree="max", gaussians=_front(rest_sigma=0.6), label="sh"), _fwd,
          needs=("sh>=1",)),
    Check("forward_colour_clamp", ("CNV-10",), "SH DC pushing channels below 0 (clamped)", "forward",
          _cases(sh_degree="zero", gaussians=_front(dc_sigma=3.0), label="colour_clamp"), _fwd),
    Check("forward_opacity", ("CNV-07",), "opacity logits from -1000 to 1000", "forward",
          _cases(gaussians=_front(logits=(-1000.0, 1000.0), n=(1, 12)), label="extreme_logits"), _fwd),
    Check("forward_opacity_scale", ("API-02", "CNV-07"), "RenderConfig.opacity_scale", "forward",
          _cases(opacity_scale=True, label="opacity_scale"), _fwd, needs=("opacity_scale",)),
    Check("forward_antialiased", ("PRJ-08",), "gsplat's antialiased opacity compensation", "forward",
          _cases(antialiased=True, gaussians=_front(scales=ss.either(ss.tiny_scales(), ss.log_scales())),
                 label="antialiased"), _fwd, needs=("antialiased",)),
    Check("forward_empty", ("API-06",), "N = 0 and all-culled scenes render the background", "forward",
          _empty_or_culled, _empty_eval),
    # ---- backward ------------------------------------------------------------------------------
    Check("backward_generic", ("RAS-07", "API-05", "COV-02", "PRJ-07", "SH-04"),
          "every gradient field for random cotangents on random scenes", "backward",
          _cases(label="generic"), _bwd(), needs=("backward",)),
    Check("backward_conic", ("RAS-08", "COV-02"),
          "anisotropic rotated Gaussians: scale and rotation gradients flow through the conic",
          "backward", _cases(gaussians=_front(scales=ss.needle_scales(max_ratio=30.0, max_long=-1.0),
                                              n=(1, 16)), label="anisotropic"),
          _bwd(("log_scales", "quats", "means")), needs=("backward",)),
    Check("backward_alpha_cap", ("RAS-10", "PRF-07"),
          "fragments above the alpha cap: the profile's gradient rule", "backward",
          _opaque, _bwd(), needs=("backward",)),
    Check("backward_frustum_clamp", ("PRJ-07", "PRJ-03"),
          "clamped Gaussians: exact depth gradient under the clamp (#75)", "backward",
          lambda ctx: ss.cases(_caps(ctx), label="off_screen",
                               gaussians=lambda c: ss.off_screen(c)), _bwd(("means", "log_scales", "quats")),
          needs=("backward",)),
    Check("backward_background", ("RAS-07", "RAS-06"),
          "non-black backgrounds with image, alpha and depth cotangents", "backward",
          _cases(background=True, label="background"), _bwd(kinds=("image", "alpha", "depth")),
          needs=("backward", "background")),
    Check("backward_sh", ("SH-04", "SH-01", "CNV-10"),
          "SH gradients: clamped channels get none, coefficients above the degree get exactly 0",
          "backward", _cases(sh_degree="partial", gaussians=_front(dc_sigma=2.0), label="sh_partial"),
          _sh_bwd, needs=("backward",)),
    Check("backward_dtype", ("CNV-11", "API-05"), "gradients in the backend's dtype and shapes",
          "backward", _cases(gaussians=_front(n=(1, 10)), label="dtype"), _bwd(), needs=("backward",)),
    Check("backward_opacity_scale", ("API-02",), "gradients with RenderConfig.opacity_scale",
          "backward", _cases(opacity_scale=True, label="opacity_scale"), _bwd(),
          needs=("backward", "opacity_scale")),
    Check("backward_antialiased", ("PRJ-08",), "gradients through the antialiasing compensation",
          "backward", _cases(antialiased=True, label="antialiased"), _bwd(),
          needs=("backward", "antialiased")),
    # ---- stages --------------------------------------------------------------------------------
    Check("stage_covariance", ("COV-01", "CNV-04", "CNV-05", "CNV-06"), "stage_covariance vs covariance_3d",
          "stage", _tiny_quats, lambda ctx, s: ev.stage(ctx, s, "covariance"), needs=("stage:covariance",)),
    Check("stage_projection", ("PRJ-04", "PRJ-01", "PRJ-02", "PRJ-03", "PRJ-05", "PRJ-06", "PRF-01",
                               "PRF-02", "PRF-03", "PRF-04"),
          "stage_projection vs project_gaussians", "stage",
          _cases(camera=dict(off_centre=True, anisotropic=True),
                 gaussians=_front(scales=ss.either(ss.log_scales(), ss.tiny_scales(), ss.needle_scales())),
                 label="projection"), lambda ctx, s: ev.stage(ctx, s, "projection"),
          needs=("stage:projection",)),
    Check("stage_sh", ("SH-02", "SH-01", "SH-03", "CNV-09", "CNV-10"), "stage_sh vs eval_sh_colors",
          "stage", _cases(gaussians=_front(rest_sigma=0.6)), lambda ctx, s: ev.stage(ctx, s, "sh"),
          needs=("stage:sh",)),
    Check("stage_composite", ("RAS-03", "RAS-01", "RAS-02", "RAS-04", "RAS-05", "RAS-06", "PRF-05",
                              "PRF-06", "PRF-08"),
          "stage_composite vs composite on the reference's 2D Gaussians", "stage",
          _cases(gaussians=_front(logits=(-3.0, 12.0))), lambda ctx, s: ev.stage(ctx, s, "composite"),
          needs=("stage:composite",)),
    # ---- invalid input ---------------------------------------------------------------------------
    Check("errors_zero_quaternion", ("CNV-05", "API-03"), "a zero quaternion raises ValueError",
          "errors", _zero_quat_scene, _zero_quat_eval, examples=0.25),
    Check("errors_invalid_input", ("API-03",),
          "NaN, wrong shapes, a non-rigid pose, fx = 0 raise ValueError", "errors",
          _invalid_scene, _invalid_eval, examples=0.5),
    # ---- reference-only ----------------------------------------------------------------------------
    Check("reference_chunking", ("RAS-09",),
          "reference-only: refgs with 2-slot chunks equals refgs with the default chunk "
          "(memory bounds cannot be observed through a backend interface)", "reference",
          _cases(gaussians=_front(n=(4, 40), scales=ss.log_scales(-2.0, -0.5))), _chunking_eval,
          examples=0.25),
] + [_hard_check(cid) for cid in HARD_CASES]


def checks_for(clauses=None) -> list[Check]:
    """Checks citing any clause in ``clauses`` (all checks when None)."""
    if clauses is None:
        return list(CHECKS)
    want = set(clauses)
    return [c for c in CHECKS if want & set(c.clauses)]


def cited_clauses() -> set[str]:
    return {cid for c in CHECKS for cid in c.clauses}


def get_check(name: str) -> Check:
    for c in CHECKS:
        if c.name == name:
            return c
    raise ValueError(f"unknown check {name!r}; known: {', '.join(c.name for c in CHECKS)}")
