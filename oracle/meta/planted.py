"""Planted-bug backends: refgs (float64, inria profile) with exactly one defect each (ORC-10).

The oracle must fail each of them with the clause id of its defect, and must pass refgs itself
(tests/test_oracle_meta.py).  They wrap refgs -- its stage functions, its public containers and,
for the two backward defects, the stage intermediates ``render`` keeps in ``RenderOutput.cache``
-- and never modify or monkeypatch it.

    no_dilation            (a) PRJ-04  the 0.3 px^2 dilation left out (a Profile with eps2d = 0)
    blend_at_cutoff        (b) RAS-05  the fragment that drops T below 1e-4 is blended
    conic_offdiag_doubled  (c) RAS-08  the original's -0.5 on dL/dconic.y "fixed" to -1 while the
                                       compensating x2 in the covariance chain stays (backward only)
    sh_band_sign           (d) CNV-09  the degree-1 SH band's sign flipped
    no_cap_gradient        (e) RAS-10  inria profile without the gradient through the alpha cap
                                       (backward only)
    half_pixel_shift       (f) CNV-08  pixels sampled at (j, i) instead of (j + 0.5, i + 0.5)

and, for the shrinker's meta-test, ``two_defects`` (backward only): under the frustum clamp the
depth term of the clamped Jacobian dropped (PRJ-07, #75), and outside it the means gradient 1.5
times too large; ``clamp_defect_only`` and ``unclamped_defect_only`` carry one each.

(c) in numbers: refgs' compositing backward returns v_B = dL/dB with the off-diagonal counted once
(RAS-08); the original stores half of it per symmetric entry and doubles it in
``computeCov2DCUDA``.  Replacing the -0.5 by -1 without removing the doubling hands the covariance
chain 2 v_B: every gradient that flows through B (scales, rotations, and the means through the
Jacobian) gets an extra v_B's worth; the forward and dL/dmeans2d are untouched.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.special import expit

import refgs
from refgs.constants import ALPHA_MIN, INRIA, T_MIN, TILE_SIZE

_LABEL = "refgs 0.1 + planted defect"


class _Planted:
    """Common capabilities: inria profile, float64, SH degree 3, no antialiasing."""

    profile = "inria"
    dtype = "float64"
    max_sh_degree = 3
    supports_antialiased = False
    supports_opacity_scale = True
    version = _LABEL
    has_backward = False

    def __init__(self, name: str, clause: str):
        self.name, self.clause = name, clause


def _forward_stages(g: refgs.Gaussians, cam: refgs.Camera, cfg: refgs.RenderConfig, colors_fn=None):
    """refgs' forward up to the 2D Gaussians: (proj, g2d, lists) (COV, PRJ, SH stages)."""
    refgs.validate_inputs(g, cam, cfg)
    profile = refgs.get_profile(cfg.profile)
    cov = refgs.covariance_3d(g.quats, g.log_scales)
    o = expit(g.opacity_logits)
    if cfg.opacity_scale is not None:
        o = o * np.asarray(cfg.opacity_scale, np.float64)
    proj = refgs.project_gaussians(g.means, cov["cov3d"], o, cam, profile, cfg.antialiased)
    deg = cfg.active_sh_degree(g.sh.shape[1])
    colors = (colors_fn or _colors)(g.means, g.sh, cam.center, deg)
    g2d = {"means2d": proj["means2d"], "conics": proj["conics"], "opacities": o * proj["comp"],
           "colors": colors, "depths": proj["depths"]}
    lists = refgs.build_tile_lists(proj["tile_rect"], proj["depths"], proj["visible"],
                                   int(cam.width), int(cam.height))
    return profile, proj, g2d, lists


def _colors(means, sh, campos, degree):
    return refgs.eval_sh_colors(means, sh, campos, degree)["colors"]


def _output(comp: dict, proj: dict, g2d: dict) -> dict:
    return {"image": comp["image"], "alpha": comp["alpha"], "depth": comp["depth"],
            "n_contrib": comp["n_contrib"], "radii": proj["radii"], "means2d": proj["means2d"],
            "depths": proj["depths"], "conics": proj["conics"], "colors": g2d["colors"]}


# ---- (a) no dilation --------------------------------------------------------------------------


class NoDilation(_Planted):
    """refgs with ``dataclasses.replace(INRIA, eps2d=0)`` (PRJ-04's dilation left out)."""

    has_backward = True
    PROFILE = dataclasses.replace(INRIA, eps2d=0.0)

    def render(self, gaussians, camera, config):
        with np.errstate(all="ignore"):
            return refgs.render(gaussians, camera, dataclasses.replace(config, profile=self.PROFILE))

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        with np.errstate(all="ignore"):
            return refgs.render_backward(out, v_image, v_alpha, v_depth)


# ---- (b) the saturating fragment blended --------------------------------------------------------


def dense_composite(g2d, proj, width, height, profile, background, blend_saturating=False) -> dict:
    """Per-pixel compositing over all Gaussians at once (RAS-01..RAS-06), optionally with the
    defect of (b): the fragment whose T(1 - alpha) falls below 1e-4 is blended before stopping."""
    n = g2d["means2d"].shape[0]
    P = width * height
    rows, cols = np.divmod(np.arange(P), width)
    order = np.lexsort((np.arange(n), g2d["depths"]))
    order = order[proj["visible"][order]]
    r = proj["tile_rect"][order]
    tx, ty = (cols // TILE_SIZE)[:, None], (rows // TILE_SIZE)[:, None]
    covered = (tx >= r[:, 0]) & (tx < r[:, 1]) & (ty >= r[:, 2]) & (ty < r[:, 3])     # (P, n)
    m = g2d["means2d"][order]
    A, B, C = (g2d["conics"][order, k] for k in range(3))
    dx = m[:, 0] - (cols[:, None] + 0.5)
    dy = m[:, 1] - (rows[:, None] + 0.5)
    power = -0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy
    alpha = np.minimum(profile.alpha_max, g2d["opacities"][order] * np.exp(np.minimum(power, 0)))
    valid = covered & (power <= 0) & (alpha >= ALPHA_MIN)
    T_after = np.cumprod(np.where(valid, 1 - alpha, 1.0), axis=1)
    stop = valid & ((T_after <= T_MIN) if profile.stop_inclusive else (T_after < T_MIN))
    first = np.where(stop.any(1), np.argmax(stop, axis=1), order.size) if order.size else np.zeros(P, int)
    pos = np.arange(order.size)[None, :]
    blended = valid & ((pos <= first[:, None]) if blend_saturating else (pos < first[:, None]))
    one_minus = np.where(blended, 1 - alpha, 1.0)
    T_before = np.cumprod(np.concatenate([np.ones((P, 1)), one_minus[:, :-1]], 1), axis=1) \
        if order.size else np.ones((P, 0))
    w = np.where(blended, alpha * T_before, 0.0)
    T_final = np.prod(one_minus, axis=1) if order.size else np.ones(P)
    image = w @ g2d["colors"][order] + T_final[:, None] * np.asarray(background, np.float64)
    listpos = np.cumsum(covered, axis=1)
    n_contrib = np.where(blended, listpos, 0).max(axis=1, initial=0)
    return {"image": image.reshape(height, width, 3), "alpha": (1 - T_final).reshape(height, width),
            "depth": (w @ g2d["depths"][order]).reshape(height, width),
            "n_contrib": n_contrib.reshape(height, width).astype(np.int32)}


class BlendAtCutoff(_Planted):
    """The fragment that would drop T below 1e-4 is blended, then the pixel stops (RAS-05)."""

    def render(self, gaussians, camera, config):
        profile, proj, g2d, _ = _forward_stages(gaussians, camera, config)
        comp = dense_composite(g2d, proj, int(camera.width), int(camera.height), profile,
                               config.background, blend_saturating=True)
        return _output(comp, proj, g2d)


# ---- (c) and (e): backward-only defects -----------------------------------------------------------


def _chain(out: refgs.RenderOutput, vc: dict) -> refgs.Gradients:
    """Compositing-stage cotangents ``vc`` -> raw-parameter gradients, through refgs' stage
    backwards (the tail of refgs.render_backward, linear in ``vc``)."""
    c = out.cache
    proj, vis = c["proj"], c["proj"]["visible"]
    g = out.gaussians
    v_opac = np.where(vis, vc["v_opacities"], 0)
    v_logits = v_opac * c["scale"] * proj["comp"] * c["o_sig"] * (1 - c["o_sig"])
    v_sh, v_means_sh = refgs.eval_sh_colors_backward(c["sh"], g.sh, np.where(vis[:, None], vc["v_colors"], 0))
    v_means2d = np.where(vis[:, None], vc["v_means2d"], 0)
    v_means, v_cov3d = refgs.project_gaussians_backward(proj, out.camera, v_means2d, vc["v_conics"],
                                                        vc["v_depths"], None)
    v_quats, v_log_scales = refgs.covariance_3d_backward(c["cov"], v_cov3d)
    return refgs.Gradients(means=v_means + v_means_sh, log_scales=v_log_scales, quats=v_quats,
                           opacity_logits=v_logits, sh=v_sh, means2d=v_means2d)


def _plus(a: refgs.Gradients, b: refgs.Gradients) -> refgs.Gradients:
    return refgs.Gradients(**{k: getattr(a, k) + getattr(b, k) for k in a.to_dict()})


def _zero_vc(n):
    z = np.zeros
    return {"v_opacities": z(n), "v_colors": z((n, 3)), "v_means2d": z((n, 2)),
            "v_conics": z((n, 3)), "v_depths": z(n)}


def _composite_vc(out, profile, v_image, v_alpha, v_depth):
    H, W = out.alpha.shape
    c = out.cache
    return refgs.composite_backward(c["g2d"], c["lists"], W, H, profile,
                                    np.asarray(out.config.background, np.float64), out.final_T,
                                    np.asarray(v_image, np.float64),
                                    None if v_alpha is None else np.asarray(v_alpha, np.float64),
                                    None if v_depth is None else np.asarray(v_depth, np.float64))


class ConicOffdiagDoubled(_Planted):
    """Backward only: the covariance chain receives 2 dL/dB (HARD-03's "fix" of #551)."""

    has_backward = True

    def render(self, gaussians, camera, config):
        return refgs.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        right = refgs.render_backward(out, v_image, v_alpha, v_depth)
        vc = _composite_vc(out, out.cache["profile"], v_image, v_alpha, v_depth)
        extra = _zero_vc(len(out.gaussians))
        extra["v_conics"][:, 1] = vc["v_conics"][:, 1]          # one more v_B
        wrong = _chain(out, extra)
        wrong = dataclasses.replace(wrong, means2d=np.zeros_like(wrong.means2d))
        return _plus(right, wrong)


class NoCapGradient(_Planted):
    """Backward only: the inria profile without the gradient through the alpha cap (RAS-10)."""

    has_backward = True
    GATED = dataclasses.replace(INRIA, grad_through_alpha_cap=False)

    def render(self, gaussians, camera, config):
        return refgs.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        right = refgs.render_backward(out, v_image, v_alpha, v_depth)
        full = _composite_vc(out, out.cache["profile"], v_image, v_alpha, v_depth)
        gated = _composite_vc(out, self.GATED, v_image, v_alpha, v_depth)
        delta = {k: gated[k] - full[k] for k in full}
        return _plus(right, _chain(out, delta))


# ---- (d) one SH band's sign ---------------------------------------------------------------------


def _colors_band1_flipped(means, sh, campos, degree):
    """SH colours with the degree-1 basis functions b1..b3 negated (CNV-09 defect)."""
    d = means - np.asarray(campos, np.float64)
    dirs = d / np.linalg.norm(d, axis=-1, keepdims=True)
    basis, _ = refgs.sh_basis(degree, dirs)
    basis = basis.copy()
    basis[:, 1:4] *= -1.0
    nb = basis.shape[1]
    rgb = np.einsum("nk,nkc->nc", basis, sh[:, :nb, :]) + refgs.constants.SH_COLOR_OFFSET
    return np.maximum(rgb, 0.0)


class ShBandSign(_Planted):
    """The degree-1 SH band enters with the opposite sign (CNV-09)."""

    def render(self, gaussians, camera, config):
        profile, proj, g2d, lists = _forward_stages(gaussians, camera, config, _colors_band1_flipped)
        comp = refgs.composite(g2d, lists, int(camera.width), int(camera.height), profile,
                               np.asarray(config.background, np.float64))
        return _output(comp, proj, g2d)


# ---- (f) half-pixel shift -------------------------------------------------------------------------


class HalfPixelShift(_Planted):
    """Pixel (i, j) sampled at (j, i) instead of its centre (j + 0.5, i + 0.5) (CNV-08)."""

    def render(self, gaussians, camera, config):
        profile, proj, g2d, lists = _forward_stages(gaussians, camera, config)
        shifted = dict(g2d, means2d=g2d["means2d"] + 0.5)     # dx = m - j = (m + 0.5) - (j + 0.5)
        comp = refgs.composite(shifted, lists, int(camera.width), int(camera.height), profile,
                               np.asarray(config.background, np.float64))
        return _output(comp, proj, g2d)


# ---- two defects told apart by the frustum clamp (the shrinker's meta-test, ORC-06) --------------


class TwoDefects(_Planted):
    """Backward only, two defects that show in the same output (dL/dmeans) and differ only by
    the frustum clamp (PRJ-03): ``under`` -- for a Gaussian clamped by the frustum the depth term
    of the clamped Jacobian is dropped (#75, PRJ-07: a Profile with ``exact_clamp_depth_grad``
    off); ``outside`` -- the means gradient of every visible unclamped Gaussian is
    :attr:`SCALE` times too large.  A shrink that crops the image until an unclamped Gaussian
    becomes clamped turns the second defect into the first."""

    has_backward = True
    NO_DEPTH_TERM = dataclasses.replace(INRIA, exact_clamp_depth_grad=False)
    #: the ``outside`` defect's factor on dL/dmeans
    SCALE = 1.5

    def __init__(self, name: str, clause: str, under: bool = True, outside: bool = True):
        super().__init__(name, clause)
        self.under, self.outside = under, outside

    def render(self, gaussians, camera, config):
        return refgs.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        src = out
        if self.under:
            src = refgs.render(out.gaussians, out.camera,
                               dataclasses.replace(out.config, profile=self.NO_DEPTH_TERM))
        grads = refgs.render_backward(src, v_image, v_alpha, v_depth)
        if self.outside:
            proj = out.cache["proj"]
            unclamped = proj["visible"] & ~(proj["clamped_x"] | proj["clamped_y"])
            means = np.array(grads.means, copy=True)
            means[unclamped] *= self.SCALE
            grads = dataclasses.replace(grads, means=means)
        return grads


no_dilation = NoDilation("planted-no-dilation", "PRJ-04")
blend_at_cutoff = BlendAtCutoff("planted-blend-at-cutoff", "RAS-05")
conic_offdiag_doubled = ConicOffdiagDoubled("planted-conic-offdiag-doubled", "RAS-08")
sh_band_sign = ShBandSign("planted-sh-band-sign", "CNV-09")
no_cap_gradient = NoCapGradient("planted-no-cap-gradient", "RAS-10")
half_pixel_shift = HalfPixelShift("planted-half-pixel-shift", "CNV-08")
two_defects = TwoDefects("planted-two-defects", "PRJ-07")
clamp_defect_only = TwoDefects("planted-clamp-defect-only", "PRJ-07", under=True, outside=False)
unclamped_defect_only = TwoDefects("planted-unclamped-defect-only", "PRJ-07", under=False, outside=True)

#: name -> (backend, the clause its defect violates, True if the defect is backward-only)
PLANTED = {
    "no_dilation": (no_dilation, "PRJ-04", False),
    "blend_at_cutoff": (blend_at_cutoff, "RAS-05", False),
    "conic_offdiag_doubled": (conic_offdiag_doubled, "RAS-08", True),
    "sh_band_sign": (sh_band_sign, "CNV-09", False),
    "no_cap_gradient": (no_cap_gradient, "RAS-10", True),
    "half_pixel_shift": (half_pixel_shift, "CNV-08", False),
}
