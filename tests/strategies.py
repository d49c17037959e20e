"""Hypothesis strategies for renderer scenes, the threshold-margin filter, and shared test helpers.

Scenes
------
:func:`scenes` draws a small random scene (a few Gaussians in front of a pinhole camera, an image
of at most 40 x 32 pixels, both profiles, optional background / antialiasing / opacity_scale).
Hypothesis draws the structure (profile, sizes, flags) and an integer seed; the arrays come from
``np.random.default_rng(seed)``, so every example is reproducible from its printed seed.

Threshold margins: the documented way to exclude the clamp band
---------------------------------------------------------------
The rendered image is a piecewise-smooth function of the parameters.  It jumps, or has a kink,
wherever a discrete decision of the model flips:

==============  =====================================================  =================
name            the quantity whose sign decides                        clause
==============  =====================================================  =================
``near``        z - near (near/far cull)                                PRJ-02, PRF-01
``frustum``     u - lim, v - lim (Jacobian clamp: a kink)               PRJ-03, PRF-02
``radius``      distance of the continuous radius to an integer (ceil) PRJ-05, PRF-04
``tiles``       tile-rectangle arguments to the nearest integer         RAS-01, PRF-08
``cull``        gsplat's off-screen and opacity culls                   PRF-04, PRF-08
``sort``        pairwise depth gaps (sort order)                        RAS-02
``sh_clamp``    rgb before the clamp at 0 (a kink)                      CNV-10, SH-04
``comp``        det0 / det of the antialiasing compensation            PRJ-08
``alpha_min``   log(o G * 255) of every evaluated fragment              RAS-04
``alpha_cap``   log(o G / cap) (a kink); inria: log(cap / o G) >= m     RAS-04, RAS-10
``t_stop``      log(T (1 - alpha) / 1e-4) of every reached fragment     RAS-05, PRF-06
==============  =====================================================  =================

:func:`threshold_distances` returns, for a rendered scene, the smallest distance of each of these
quantities to its threshold, in the units of the table (depth units, tangent units, pixels, log
units).  :func:`far_from_thresholds` accepts a scene when every distance is at least ``margin``
(default :data:`MARGIN`).  Finite-difference checks draw scenes with this filter: a
central difference with step ``h`` (and ``2h`` for Richardson) moves every quantity of the table
by at most ``S * 2h``, where S is bounded by the scene ranges of :func:`scenes` (projected sigma
>= 1.2 px, f / z <= 20: S < 60), so with ``FD_STEP = 4e-6`` no decision flips inside the
difference stencil when ``MARGIN = 1e-3``.  Scenes that fail the filter are rejected with
``hypothesis.assume``; the filter is the one place where "away from thresholds" is defined.
Tests that probe a threshold itself build the scene by hand instead (test_stages_forward.py).

One entry is one-sided: the inria profile passes the gradient through the alpha cap as if alpha
were o G (RAS-10, PRF-07), which is *not* the derivative of min(cap, o G).  A finite-difference
check of the inria profile therefore needs every fragment strictly below the cap, and for inria
``alpha_cap`` is the signed log(cap / o G) (negative above the cap); the cap's own gradient rule is
tested by hand (test_backward_fd.py::test_alpha_cap_gradient_per_profile).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace

import numpy as np
from hypothesis import settings
from hypothesis import strategies as st

import refgs
from refgs import Camera, Gaussians, RenderConfig
from refgs.constants import ALPHA_MIN, SH_C0, T_MIN, TILE_SIZE, get_profile
from refgs.projection import frustum_limits

#: Default distance (in the units of the table above) that a scene must keep from every
#: discontinuity of the model before a finite-difference check is trusted on it.
MARGIN = 1e-3
#: Central-difference step in raw-parameter units (with a 2h companion for Richardson).
FD_STEP = 4e-6
#: Step for stage functions checked on inputs that are smooth over a much wider neighbourhood
#: (covariance, SH, projection away from the clamp): Richardson's O(h^4) truncation is still
#: far below 1e-6 and the rounding noise (~1e-16 |L| / h) is 25 times smaller than with FD_STEP.
FD_STEP_SMOOTH = 1e-4
#: Gradient tolerance (common.md / issue 2): relative error <= 1e-6.
FD_RTOL = 1e-6
#: Entries whose finite difference is below this fraction of the field's largest one are
#: checked only in the field-wise norm (their relative error is dominated by the rounding
#: noise of the loss, ~1e-16 |L| / h).
FD_TINY_FRACTION = 1e-3
#: Absolute floor of the field scale: a field whose largest finite difference is below this is
#: compared in absolute terms (an identically-zero gradient must be exactly tiny).
FD_ABS_FLOOR = 1e-10
#: Rounding noise of a central difference of a loss L is about eps * sum|terms of L| / h; the
#: whole-render checks allow this many times that as an absolute floor (it matters only for
#: gradients that vanish identically, e.g. the quaternion of an isotropic Gaussian).
FD_NOISE_FACTOR = 10.0

PROFILE_NAMES = ("inria", "gsplat")


def max_examples(ci: int) -> int:
    """Examples for one property: ``ci`` in the default (ci) hypothesis profile; under another
    profile (``HYPOTHESIS_PROFILE=release``) the profile's larger count (tests/conftest.py)."""
    if os.environ.get("HYPOTHESIS_PROFILE", "ci") == "ci":
        return ci
    return max(ci, settings.default.max_examples)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Scene:
    """A renderable scene: Gaussians, camera, config (plus the seed it was drawn from)."""

    gaussians: Gaussians
    camera: Camera
    config: RenderConfig
    seed: int = 0

    def render(self, gaussians: Gaussians | None = None, **config_changes) -> refgs.RenderOutput:
        cfg = replace(self.config, **config_changes) if config_changes else self.config
        return refgs.render(self.gaussians if gaussians is None else gaussians, self.camera, cfg)


def make_camera(rng: np.random.Generator, width: int, height: int, *, f_range=(16.0, 26.0),
                principal_jitter: float = 3.0) -> Camera:
    """A look-at camera ~3.5 units from the origin, random orientation, off-centre cx, cy."""
    eye = rng.normal(size=3)
    eye *= 3.5 / np.linalg.norm(eye)
    target = 0.2 * rng.normal(size=3)
    up = rng.normal(size=3)
    f = rng.uniform(*f_range)
    cx = width / 2 + rng.uniform(-principal_jitter, principal_jitter)
    cy = height / 2 + rng.uniform(-principal_jitter, principal_jitter)
    return Camera.look_at(eye, target, up=up, fx=f, fy=f * rng.uniform(0.9, 1.1),
                          width=width, height=height, cx=cx, cy=cy)


def camera_to_world_points(camera: Camera, t_cam: np.ndarray) -> np.ndarray:
    """World points whose camera-space coordinates are ``t_cam`` (N,3) (inverse of PRJ-01)."""
    R, tw = camera.rotation, camera.translation
    return (t_cam - tw) @ R


def place_gaussians(rng: np.random.Generator, camera: Camera, n: int, *, sh_degree: int = 1,
                    sigma_px=(1.2, 3.5), depth=(2.0, 4.5), logits=(-1.5, 2.5),
                    offscreen: float = 0.1, anisotropy: float = 0.5,
                    sh_spread: float = 0.1, k: int | None = None) -> Gaussians:
    """n Gaussians placed by their screen position (a fraction ``offscreen`` beyond each edge),
    depth, and projected size sigma_px (pixels); random rotations and anisotropy.

    Returns float64 Gaussians with K = (sh_degree + 1)**2 (or ``k``) SH coefficients whose DC
    term gives a base colour in [0.2, 0.9] and whose higher bands have spread ``sh_spread``.
    """
    W, H = camera.width, camera.height
    u = rng.uniform(-offscreen * W, (1 + offscreen) * W, n)
    v = rng.uniform(-offscreen * H, (1 + offscreen) * H, n)
    z = rng.uniform(*depth, n)
    t_cam = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], -1)
    means = camera_to_world_points(camera, t_cam)
    s_world = rng.uniform(*sigma_px, n) * z / camera.fx
    log_scales = np.log(s_world)[:, None] + rng.uniform(-anisotropy, anisotropy, (n, 3))
    quats = rng.normal(size=(n, 4))
    quats *= rng.uniform(0.5, 2.0, (n, 1)) / np.linalg.norm(quats, axis=1, keepdims=True)
    kk = (sh_degree + 1) ** 2 if k is None else k
    sh = sh_spread * rng.normal(size=(n, kk, 3))
    sh[:, 0, :] = (rng.uniform(0.2, 0.9, (n, 3)) - 0.5) / SH_C0
    return Gaussians(means, log_scales, quats, rng.uniform(*logits, n), sh)


@st.composite
def scenes(draw, *, profiles=PROFILE_NAMES, n=(1, 3), width=(16, 40), height=(12, 32),
           sh_degree=(0, 3), backgrounds=("black", "white", "random"),
           antialiased=(False, True), opacity_scale=(False, True), sigma_px=(1.2, 3.5),
           logits=(-1.5, 2.5), offscreen=0.1) -> Scene:
    """A random small scene (see the module docstring).  ``antialiased`` only applies to the
    gsplat profile (API-02); ``opacity_scale=(False, True)`` sometimes draws a per-Gaussian factor
    in [0.6, 1.4]."""
    profile = draw(st.sampled_from(profiles), label="profile")
    count = draw(st.integers(*n), label="n")
    W = draw(st.integers(*width), label="width")
    H = draw(st.integers(*height), label="height")
    deg = draw(st.integers(*sh_degree), label="sh_degree")
    bg_kind = draw(st.sampled_from(backgrounds), label="background")
    aa = profile == "gsplat" and draw(st.sampled_from(antialiased), label="antialiased")
    use_scale = draw(st.sampled_from(opacity_scale), label="opacity_scale")
    seed = draw(st.integers(0, 2**32 - 1), label="seed")
    rng = np.random.default_rng(seed)
    cam = make_camera(rng, W, H)
    g = place_gaussians(rng, cam, count, sh_degree=deg, sigma_px=sigma_px, logits=logits,
                        offscreen=offscreen)
    bg = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0),
          "random": tuple(rng.uniform(0, 1, 3))}[bg_kind]
    scale = rng.uniform(0.6, 1.4, count) if use_scale else None
    cfg = RenderConfig(profile=profile, background=bg, antialiased=aa, opacity_scale=scale)
    return Scene(g, cam, cfg, seed)


# ------------------------------------------------------------------------------------------
# Brute-force per-pixel compositing (math.md section 4, written independently of refgs.rasterize)
# ------------------------------------------------------------------------------------------

def pixel_tile_lists(tile_rect: np.ndarray, visible: np.ndarray, depths: np.ndarray,
                     width: int, height: int) -> dict[tuple[int, int], list[int]]:
    """{(tile_x, tile_y): Gaussian indices covering that tile, sorted by (depth, index)} (RAS-01/02)."""
    gx = (width + TILE_SIZE - 1) // TILE_SIZE
    gy = (height + TILE_SIZE - 1) // TILE_SIZE
    lists = {}
    for ty in range(gy):
        for tx in range(gx):
            members = [k for k in range(len(visible)) if visible[k]
                       and tile_rect[k, 0] <= tx < tile_rect[k, 1]
                       and tile_rect[k, 2] <= ty < tile_rect[k, 3]]
            lists[(tx, ty)] = sorted(members, key=lambda k: (float(depths[k]), k))
    return lists


def composite_loop(means2d, conics, opacities, colors, depths, tile_rect, visible, width, height,
                   profile, background) -> dict:
    """The compositing model of math.md section 4 as a literal per-pixel loop.

    Arithmetic happens in numpy scalars of the dtype of ``means2d`` (float32 or float64), one
    operation at a time in the order the spec writes them, so the loop is also a float32
    reference.  Returns image (H,W,3), alpha, depth, n_contrib, final_T (H,W), ``blended`` (a dict
    {(i, j): [Gaussian ids blended at that pixel, front to back]}) and the fragment distances
    ``alpha_min``, ``alpha_cap``, ``t_stop`` of the module docstring (minimum over the fragments
    the loop reached, computed in float64).
    """
    prof = get_profile(profile) if isinstance(profile, str) else profile
    ft = np.asarray(means2d).dtype.type
    cap = ft(prof.alpha_max)
    amin, tmin, one, half = ft(ALPHA_MIN), ft(T_MIN), ft(1), ft(0.5)
    lists = pixel_tile_lists(tile_rect, visible, depths, width, height)
    m2 = np.asarray(means2d)
    con = np.asarray(conics, m2.dtype)
    opa = np.asarray(opacities, m2.dtype)
    col = np.asarray(colors, m2.dtype)
    dep = np.asarray(depths, m2.dtype)
    bgc = np.asarray(background, m2.dtype)
    image = np.zeros((height, width, 3), m2.dtype)
    alpha_img = np.zeros((height, width), m2.dtype)
    depth_img = np.zeros((height, width), m2.dtype)
    n_contrib = np.zeros((height, width), np.int64)
    final_T = np.ones((height, width), m2.dtype)
    blended = {}
    d_min = d_cap = d_stop = math.inf
    for i in range(height):
        for j in range(width):
            px, py = ft(j + 0.5), ft(i + 0.5)
            T, C, D, last, used = one, np.zeros(3, m2.dtype), ft(0), 0, []
            for pos, k in enumerate(lists[(j // TILE_SIZE, i // TILE_SIZE)], start=1):
                A, B, Cc = con[k]
                dx = m2[k, 0] - px
                dy = m2[k, 1] - py
                power = -half * (A * dx * dx + Cc * dy * dy) - B * dx * dy
                if power > 0:
                    continue
                oG = opa[k] * np.exp(power)
                if oG > 0:
                    d_min = min(d_min, abs(math.log(float(oG) * 255.0)))
                    cap_gap = math.log(float(cap) / float(oG))
                    d_cap = min(d_cap, cap_gap if prof.grad_through_alpha_cap else abs(cap_gap))
                alpha = min(cap, oG)
                if alpha < amin:
                    continue
                test_T = T * (one - alpha)
                d_stop = min(d_stop, abs(math.log(float(test_T) / T_MIN)) if test_T > 0 else 0.0)
                stop = (test_T <= tmin) if prof.stop_inclusive else (test_T < tmin)
                if stop:
                    break
                C = C + col[k] * (alpha * T)
                D = D + dep[k] * (alpha * T)
                T = test_T
                last = pos
                used.append(k)
            image[i, j] = C + T * bgc
            alpha_img[i, j] = one - T
            depth_img[i, j] = D
            n_contrib[i, j] = last
            final_T[i, j] = T
            blended[(i, j)] = used
    return {"image": image, "alpha": alpha_img, "depth": depth_img, "n_contrib": n_contrib,
            "final_T": final_T, "blended": blended,
            "alpha_min": d_min, "alpha_cap": d_cap, "t_stop": d_stop}


def composite_loop_of(out: refgs.RenderOutput) -> dict:
    """:func:`composite_loop` on the per-Gaussian quantities of a float64 RenderOutput."""
    proj = out.cache["proj"]
    return composite_loop(out.means2d, out.conics, out.opacities, out.colors, out.depths,
                          proj["tile_rect"], out.visible, out.camera.width, out.camera.height,
                          out.cache["profile"], out.config.background)


# ------------------------------------------------------------------------------------------
# Threshold distances (the margin filter)
# ------------------------------------------------------------------------------------------

def _frac_distance(x: np.ndarray) -> float:
    """Smallest distance of the entries of x to an integer (inf for an empty array)."""
    x = np.asarray(x, float).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.inf
    return float(np.min(np.abs(x - np.round(x))))


def _min_abs(x) -> float:
    x = np.asarray(x, float).ravel()
    x = x[np.isfinite(x)]
    return float(np.min(np.abs(x))) if x.size else math.inf


def threshold_distances(out: refgs.RenderOutput) -> dict[str, float]:
    """Smallest distance of each discontinuity quantity of the module table to its threshold."""
    prof = out.cache["profile"]
    proj = out.cache["proj"]
    cam = out.camera
    W, H = cam.width, cam.height
    t = proj["t"]
    z = t[:, 2]
    d = {"near": _min_abs(z - prof.near)}
    live = z > prof.near * 0.5                  # rows whose projection is meaningful
    zl = np.where(live, z, 1.0)
    u, v = t[:, 0] / zl, t[:, 1] / zl
    lnx, lpx, lny, lpy = frustum_limits(cam, prof, np.dtype(np.float64))
    d["frustum"] = _min_abs(np.concatenate([(u + lnx)[live], (u - lpx)[live],
                                            (v + lny)[live], (v - lpy)[live]]))
    a, b, c = out.cov2d[:, 0], out.cov2d[:, 1], out.cov2d[:, 2]
    m = out.means2d
    o_eff = out.cache["o_sig"] * out.cache["scale"] * proj["comp"]
    cull = []
    if prof.radius_rule == "eig":
        mid = 0.5 * (a + c)
        det = a * c - b * b
        r_cont = prof.radius_sigma * np.sqrt(mid + np.sqrt(np.maximum(prof.eig_floor, mid * mid - det)))
        rx = ry = np.ceil(r_cont)
        d["radius"] = _frac_distance(r_cont[live])
        px, py = m[:, 0] - 0.5, m[:, 1] - 0.5
        args = [(px - rx) / TILE_SIZE, (px + rx + TILE_SIZE - 1) / TILE_SIZE,
                (py - ry) / TILE_SIZE, (py + ry + TILE_SIZE - 1) / TILE_SIZE]
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            log_o = np.log(o_eff * 255.0)
            extend = np.minimum(prof.radius_sigma, np.sqrt(2.0 * np.maximum(log_o, 0)))
        rxc, ryc = extend * np.sqrt(a), extend * np.sqrt(c)
        rx, ry = np.ceil(rxc), np.ceil(ryc)
        d["radius"] = _frac_distance(np.concatenate([rxc[live], ryc[live]]))
        args = [m[:, 0] / TILE_SIZE - rx / TILE_SIZE, m[:, 0] / TILE_SIZE + rx / TILE_SIZE,
                m[:, 1] / TILE_SIZE - ry / TILE_SIZE, m[:, 1] / TILE_SIZE + ry / TILE_SIZE]
        cull += [log_o[live], (m[:, 0] + rx)[live], (m[:, 0] - rx - W)[live],
                 (m[:, 1] + ry)[live], (m[:, 1] - ry - H)[live]]
    d["tiles"] = TILE_SIZE * _frac_distance(np.concatenate([x[live] for x in args]))
    d["cull"] = _min_abs(np.concatenate(cull)) if cull else math.inf
    zv = np.sort(z[out.visible])
    d["sort"] = float(np.min(np.diff(zv))) if zv.size > 1 else math.inf
    sh = out.cache["sh"]
    nb = sh["basis"].shape[1]
    rgb = np.einsum("nk,nkc->nc", sh["basis"], out.gaussians.sh[:, :nb, :]) + 0.5
    d["sh_clamp"] = _min_abs(rgb[out.visible])
    if out.config.antialiased:
        det0 = proj["det0"]
        d["comp"] = _min_abs((det0 / proj["det"])[live])
    else:
        d["comp"] = math.inf
    loop = composite_loop_of(out)
    d.update({k: loop[k] for k in ("alpha_min", "alpha_cap", "t_stop")})
    return d


def far_from_thresholds(out: refgs.RenderOutput, margin: float = MARGIN) -> bool:
    """True when every threshold distance of the scene is at least ``margin`` (module docstring)."""
    return all(v >= margin for v in threshold_distances(out).values())


# ------------------------------------------------------------------------------------------
# Finite differences
# ------------------------------------------------------------------------------------------

def fd_derivative(f, x: np.ndarray, index, h: float = FD_STEP) -> float:
    """d f / d x[index] by a Richardson-extrapolated central difference (error O(h^4)).

    f maps an array shaped like x to a float; x is not modified.
    """
    def central(step):
        xp = x.copy()
        xm = x.copy()
        xp[index] += step
        xm[index] -= step
        return (f(xp) - f(xm)) / (2 * step)
    return (4 * central(h) - central(2 * h)) / 3


def fd_gradient(f, x: np.ndarray, indices=None, h: float = FD_STEP) -> np.ndarray:
    """Finite-difference gradient of f at x over ``indices`` (all by default); NaN elsewhere."""
    x = np.asarray(x, np.float64)
    out = np.full(x.shape, np.nan)
    idx = list(np.ndindex(x.shape)) if indices is None else indices
    for i in idx:
        out[i] = fd_derivative(f, x, i, h)
    return out


def assert_grad_close(analytic, fd, name: str, rtol: float = FD_RTOL, atol: float = 0.0) -> None:
    """Compare an analytic gradient with finite differences (NaN entries of fd are skipped).

    Field-wise: |an - fd| <= max(rtol * max(|fd|_inf, FD_ABS_FLOOR), atol) for every entry.
    Element-wise: |an - fd| <= rtol * |fd| where |fd| >= FD_TINY_FRACTION * |fd|_inf and
    |fd| >= atol / rtol (above the noise floor).
    """
    analytic = np.asarray(analytic, np.float64)
    fd = np.asarray(fd, np.float64)
    sel = ~np.isnan(fd)
    an, fv = analytic[sel], fd[sel]
    assert np.all(np.isfinite(an)), f"{name}: non-finite analytic gradient"
    if fv.size == 0:
        return
    scale = max(float(np.max(np.abs(fv))), FD_ABS_FLOOR)
    err = np.abs(an - fv)
    worst = int(np.argmax(err))
    assert err[worst] <= max(rtol * scale, atol), (
        f"{name}: |analytic - fd| = {err[worst]:.3e} > max({rtol:g} * {scale:.3e}, {atol:.1e}) "
        f"(analytic {an[worst]!r}, fd {fv[worst]!r})")
    big = (np.abs(fv) >= FD_TINY_FRACTION * scale) & (np.abs(fv) * rtol >= atol)
    if np.any(big):
        rel = err[big] / np.abs(fv[big])
        k = int(np.argmax(rel))
        assert rel[k] <= rtol, (f"{name}: element-wise relative error {rel[k]:.3e} > {rtol:g} "
                                f"(analytic {an[big][k]!r}, fd {fv[big][k]!r})")


def random_cotangents(rng: np.random.Generator, height: int, width: int, *, alpha=True,
                      depth=True) -> dict:
    """Random v_image (H,W,3) and optionally v_alpha, v_depth (H,W) for a scalar test loss."""
    return {"v_image": rng.normal(size=(height, width, 3)),
            "v_alpha": rng.normal(size=(height, width)) if alpha else None,
            "v_depth": rng.normal(size=(height, width)) if depth else None}


def scalar_loss(out: refgs.RenderOutput, cot: dict) -> float:
    """L = <v_image, image> + <v_alpha, alpha> + <v_depth, depth> (the cotangents' loss)."""
    L = float(np.sum(cot["v_image"] * out.image))
    if cot.get("v_alpha") is not None:
        L += float(np.sum(cot["v_alpha"] * out.alpha))
    if cot.get("v_depth") is not None:
        L += float(np.sum(cot["v_depth"] * out.depth))
    return L


def fd_noise_floor(out: refgs.RenderOutput, cot: dict, h: float) -> float:
    """FD_NOISE_FACTOR * eps * sum|terms of the loss| / h: the rounding noise of a central
    difference of :func:`scalar_loss` with step h (an absolute floor for assert_grad_close)."""
    terms = np.sum(np.abs(cot["v_image"] * out.image))
    for key, img in (("v_alpha", out.alpha), ("v_depth", out.depth)):
        if cot.get(key) is not None:
            terms += np.sum(np.abs(cot[key] * img))
    return FD_NOISE_FACTOR * np.finfo(np.float64).eps * float(terms) / h


def render_fd_check(scene: Scene, cot: dict, *, rng: np.random.Generator, fields=None,
                    sh_samples: int = 6, h: float = FD_STEP, rtol: float = FD_RTOL) -> None:
    """Check ``render_backward`` against finite differences of the whole render (float64).

    Every entry of means, log_scales, quats, opacity_logits is differenced; of ``sh`` (linear in
    the loss away from the clamp) a random sample of ``sh_samples`` entries of the active bands.
    """
    g = scene.gaussians
    out = scene.render()
    grads = refgs.render_backward(out, cot["v_image"], cot.get("v_alpha"), cot.get("v_depth"))
    for arr in (out.image, out.alpha, out.depth, *grads.to_dict().values()):
        assert np.all(np.isfinite(arr)), "non-finite forward or backward output"
    fields = fields or Gaussians.FIELDS
    atol = fd_noise_floor(out, cot, h)
    for name in fields:
        x = getattr(g, name)

        def f(xx, name=name):
            return scalar_loss(scene.render(g.replace(**{name: xx})), cot)
        if name == "sh":
            nb = out.cache["sh"]["basis"].shape[1]
            all_idx = [(i, k, ch) for i in range(x.shape[0]) for k in range(nb) for ch in range(3)]
            pick = rng.choice(len(all_idx), size=min(sh_samples, len(all_idx)), replace=False)
            idx = [all_idx[p] for p in pick]
        else:
            idx = None
        fd = fd_gradient(f, x, idx, h)
        assert_grad_close(getattr(grads, name), fd, f"d L / d {name}", rtol, atol)


# ------------------------------------------------------------------------------------------
# The original rasterizer's internal conic-gradient convention (peers.md 1.9, hard case 3)
# ------------------------------------------------------------------------------------------

def inria_dL_dconic(dx, dy, G, dL_dG):
    """The original's per-fragment ``dL_dconic2D`` (backward.cu render): (x, y, w) slots.

    x = -0.5 G dx^2 dL/dG, y = -0.5 G dx dy dL/dG (the gradient w.r.t. *each* of the two
    symmetric off-diagonal entries), w = -0.5 G dy^2 dL/dG.
    """
    return (-0.5 * G * dx * dx * dL_dG, -0.5 * G * dx * dy * dL_dG, -0.5 * G * dy * dy * dL_dG)


def inria_dL_dcov2d(a, b, c, g_x, g_y, g_w, denom_eps: float = 0.0):
    """The original's computeCov2DCUDA step from dL/dconic (its convention) to dL/d(a, b, c).

    ``dL_db = denom2inv * 2 * (b c g_x - (denom + 2 b^2) g_y + a b g_w)`` with the factor 2
    that compensates the -0.5 of :func:`inria_dL_dconic`.  The original uses
    ``denom2inv = 1 / (denom^2 + 1e-7)``; ``denom_eps`` (default 0: the exact derivative) is that
    regulariser.
    """
    denom = a * c - b * b
    inv = 1.0 / (denom * denom + denom_eps)
    dL_da = inv * (-c * c * g_x + 2 * b * c * g_y + (denom - a * c) * g_w)
    dL_dc = inv * (-a * a * g_w + 2 * a * b * g_y + (denom - a * c) * g_x)
    dL_db = inv * 2 * (b * c * g_x - (denom + 2 * b * b) * g_y + a * b * g_w)
    return dL_da, dL_db, dL_dc
