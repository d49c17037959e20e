"""Forward stages at and around every threshold, and the compositing against a per-pixel loop.

Clauses: PRJ-02/PRF-01 (near/far), PRJ-03/PRF-02 (frustum clamp), PRJ-05/PRF-04 (radii),
RAS-01/PRF-08 (tile coverage), RAS-02 (sort), RAS-03 (power > 0), RAS-04/PRF-05 (1/255, cap),
RAS-05/PRF-06 (transmittance stop), RAS-06 (outputs), RAS-09 (chunking), SH-01 (extra
coefficients), API-06 (empty / all-culled scenes).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings

import refgs
import refgs.rasterize as rasterize
from refgs import Camera, Gaussians, RenderConfig, render, render_backward
from refgs.constants import ALPHA_MIN, GSPLAT, INRIA, SH_C0, T_MIN, TILE_SIZE
from refgs.projection import frustum_limits

from strategies import (composite_loop_of, make_camera, max_examples, pixel_tile_lists,
                        place_gaussians, scenes)

W, H = 48, 32
F = 32.0


def identity_camera(fx=F, cx=W / 2, cy=H / 2, width=W, height=H) -> Camera:
    return Camera(np.eye(4), np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]]), width, height)


def gaussians_at(means, scales, logits=0.0, rgb=(0.7, 0.5, 0.3), quats=None, dtype=np.float64):
    means = np.atleast_2d(np.asarray(means, float))
    n = means.shape[0]
    scales = np.broadcast_to(np.asarray(scales, float), (n, 3))
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = (np.broadcast_to(np.asarray(rgb, float), (n, 3)) - 0.5) / SH_C0
    q = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else np.asarray(quats, float)
    g = Gaussians(means, np.log(scales), q, np.broadcast_to(np.asarray(logits, float), (n,)).copy(), sh)
    return g.astype(dtype)


def logit(o):
    return math.log(o / (1 - o))


# ------------------------------------------------------------------------------------------
# Hand-made 2D stacks on one pixel (composite() called directly, exact alphas)
# ------------------------------------------------------------------------------------------

def pixel_stack(alphas, profile, colors=None, background=(0.0, 0.0, 0.0), depths=None):
    """Gaussians all centred on the centre of pixel (8, 8) of a 16 x 16 image, so G = 1 there
    and alpha = min(cap, opacity) exactly; front to back in the given order (RAS-02)."""
    n = len(alphas)
    prof = refgs.get_profile(profile)
    g2d = {"means2d": np.full((n, 2), 8.5), "conics": np.tile([0.5, 0.0, 0.5], (n, 1)),
           "opacities": np.asarray(alphas, float),
           "colors": np.ones((n, 3)) if colors is None else np.asarray(colors, float),
           "depths": np.arange(1.0, n + 1) if depths is None else np.asarray(depths, float)}
    rect = np.tile([0, 1, 0, 1], (n, 1))
    lists = refgs.build_tile_lists(rect, g2d["depths"], np.ones(n, bool), 16, 16)
    out = refgs.composite(g2d, lists, 16, 16, prof, np.asarray(background, float))
    return out, g2d, lists


# ------------------------------------------------------------------------------------------
# PRJ-02 / PRF-01 near and far planes
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_near_plane_inria(dtype):
    """PRJ-02/PRF-01 inria: culled iff z <= 0.2 (compared in the working dtype)."""
    cam = identity_camera()
    z0 = dtype(0.2)
    zs = [np.nextafter(z0, dtype(0)), z0, np.nextafter(z0, dtype(1)), dtype(0.25)]
    g = gaussians_at([[0.0, 0.0, z] for z in zs], 0.002, dtype=dtype)
    out = render(g, cam, RenderConfig(profile="inria"))
    assert out.visible.tolist() == [False, False, True, True]
    assert out.radii[:2].tolist() == [[0, 0], [0, 0]] and np.all(out.radii[2:] > 0)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_near_far_gsplat(dtype):
    """PRJ-02/PRF-01 gsplat: culled iff z < 0.01 or z > 1e10 (z = 0.01 and z = 1e10 are kept)."""
    cam = identity_camera()
    near, far = dtype(0.01), dtype(1e10)
    zs = [np.nextafter(near, dtype(0)), near, np.nextafter(near, dtype(1)),
          far, np.nextafter(far, dtype(np.inf))]
    g = gaussians_at([[0.0, 0.0, z] for z in zs], 1e-4, logits=3.0, dtype=dtype)
    out = render(g, cam, RenderConfig(profile="gsplat"))
    assert out.visible.tolist() == [False, True, True, True, False]


# ------------------------------------------------------------------------------------------
# PRJ-03 / PRF-02 frustum clamp
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_frustum_clamp_jacobian_only(profile):
    """PRJ-03: the Jacobian uses u = clip(tx/tz, -lim_neg, lim_pos); means2d uses the unclamped
    point (CNV-08); exactly on the limit is not clamped (strict)."""
    cam = identity_camera(cx=20.0, cy=14.0)      # off-centre: the gsplat limits are asymmetric
    prof = refgs.get_profile(profile)
    lnx, lpx, lny, lpy = frustum_limits(cam, prof, np.dtype(np.float64))
    z = 2.0
    us = [1.5 * lpx, -1.5 * lnx, lpx, 0.3]
    vs = [0.1, -2.0 * lny, 1.2 * lpy, -lny]
    g = gaussians_at([[u * z, v * z, z] for u, v in zip(us, vs)], [0.6, 0.4, 0.3],
                     quats=[[0.9, 0.2, -0.3, 0.1]] * 4)
    out = render(g, cam, RenderConfig(profile=profile))
    proj = out.cache["proj"]
    assert np.allclose(out.means2d[:, 0], F * np.array(us) + 20.0, rtol=1e-14)
    assert np.allclose(out.means2d[:, 1], F * np.array(vs) + 14.0, rtol=1e-14)
    u_c = np.clip(us, -lnx, lpx)
    v_c = np.clip(vs, -lny, lpy)
    assert proj["clamped_x"].tolist() == [True, True, False, False]
    assert proj["clamped_y"].tolist() == [False, True, True, False]
    J = np.zeros((4, 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = F / z
    J[:, 0, 2] = -F * u_c / z
    J[:, 1, 2] = -F * v_c / z
    assert np.allclose(proj["J"], J, rtol=1e-14, atol=1e-14)
    cov3d = out.cache["cov"]["cov3d"]
    cov2d = J @ cov3d @ np.swapaxes(J, 1, 2)
    assert np.allclose(out.cov2d[:, 0], cov2d[:, 0, 0] + 0.3, rtol=1e-13)
    assert np.allclose(out.cov2d[:, 1], cov2d[:, 0, 1], rtol=1e-13, atol=1e-13)
    assert np.allclose(out.cov2d[:, 2], cov2d[:, 1, 1] + 0.3, rtol=1e-13)
    if profile == "inria":                        # symmetric limits, cx ignored
        assert lnx == lpx == pytest.approx(1.3 * W / (2 * F))


# ------------------------------------------------------------------------------------------
# COV-01, PRJ-01, PRJ-04 / PRF-03, PRJ-06, SH-02, SH-03
# ------------------------------------------------------------------------------------------

def test_covariance_3d_forward():
    """COV-01: Sigma = R S S^T R^T (R from scipy's rotation of the normalised quaternion),
    symmetric to the last bit."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(21)
    q = rng.normal(size=(8, 4)) * rng.uniform(0.1, 5.0, (8, 1))
    ls = rng.uniform(-3, 1, (8, 3))
    fwd = refgs.covariance_3d(q, ls)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    S = np.exp(ls)
    expected = R @ (S[:, :, None] ** 2 * np.eye(3)) @ np.swapaxes(R, 1, 2)
    assert np.allclose(fwd["cov3d"], expected, rtol=1e-13, atol=1e-15)
    assert np.array_equal(fwd["cov3d"], np.swapaxes(fwd["cov3d"], 1, 2))
    assert np.allclose(fwd["scales"], S, rtol=1e-15)


def test_world_to_camera_and_depth():
    """PRJ-01: t = R_w mu + t_w and Sigma_c = R_w Sigma R_w^T; PRJ-06: depths = t_z (camera z,
    not the Euclidean distance)."""
    rng = np.random.default_rng(22)
    cam = make_camera(rng, 32, 24)
    g = place_gaussians(rng, cam, 5, offscreen=0.3)
    out = render(g, cam)
    Rw, tw = cam.rotation, cam.translation
    t = g.means @ Rw.T + tw
    proj = out.cache["proj"]
    assert np.allclose(proj["t"], t, rtol=1e-14, atol=1e-14)
    assert np.allclose(out.depths, t[:, 2], rtol=1e-14)
    assert not np.allclose(out.depths, np.linalg.norm(g.means - cam.center, axis=1))
    cov = out.cache["cov"]["cov3d"]
    assert np.allclose(proj["cov_cam"], Rw @ cov @ Rw.T, rtol=1e-13, atol=1e-15)


def test_conic_and_determinant_rule():
    """PRJ-04: conic = inverse of the dilated 2D covariance; PRF-03: inria culls det == 0 only
    (a negative determinant is kept), gsplat culls det <= 0 (stage API, crafted covariances)."""
    rng = np.random.default_rng(23)
    cam = make_camera(rng, 32, 24)
    g = place_gaussians(rng, cam, 6)
    out = render(g, cam)
    for (a, b, c), (A, B, C) in zip(out.cov2d, out.conics):
        assert np.allclose(np.array([[A, B], [B, C]]) @ np.array([[a, b], [b, c]]), np.eye(2),
                           atol=1e-12)
    # camera at the origin, f / z = 16 (exact): Sigma_2D = 256 Sigma_c[:2, :2]
    cam0 = identity_camera(fx=32.0, cx=16.0, cy=16.0, width=32, height=32)
    means = np.array([[0.0, 0.0, 2.0]] * 3)
    cov = np.zeros((3, 3, 3))
    cov[:, 1, 1] = 1.0 / 256
    cov[:, 2, 2] = 0.01
    cov[0, 0, 0] = 1.0 / 256                     # a = 1.3: regular
    cov[1, 0, 0] = -0.3 / 256                    # a = 0 exactly: det == 0
    cov[2, 0, 0] = -0.5 / 256                    # a = -0.2: det < 0
    o = np.full(3, 0.9)
    fi = refgs.project_gaussians(means, cov, o, cam0, INRIA)
    fg = refgs.project_gaussians(means, cov, o, cam0, GSPLAT)
    assert fi["cov2d"][1, 0] == 0.0 and fi["cov2d"][2, 0] < 0
    assert fi["visible"].tolist() == [True, False, True]
    assert fg["visible"].tolist() == [True, False, False]


def test_sh_basis_derivatives_and_view_direction():
    """SH-02: sh_basis returns the values and their x, y, z derivatives (checked by finite
    differences); SH-03: the direction is normalize(mean - camera centre), centre = -R^T t."""
    rng = np.random.default_rng(24)
    d = rng.normal(size=(7, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for deg in range(4):
        basis, dbasis = refgs.sh_basis(deg, d)
        assert basis.shape == (7, (deg + 1) ** 2) and dbasis.shape == (7, (deg + 1) ** 2, 3)
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd = (refgs.sh_basis(deg, d + e)[0] - refgs.sh_basis(deg, d - e)[0]) / (2 * h)
            assert np.allclose(dbasis[:, :, k], fd, rtol=1e-7, atol=1e-8)
    cam = make_camera(rng, 32, 24)
    g = place_gaussians(rng, cam, 4, sh_degree=1, sh_spread=0.5)
    out = render(g, cam)
    xi = g.means + cam.rotation.T @ cam.translation             # mean - (-R^T t)
    dirs = xi / np.linalg.norm(xi, axis=1, keepdims=True)
    x, y, z = dirs.T
    C0, C1 = refgs.constants.SH_C0, refgs.constants.SH_C1
    rgb = (C0 * g.sh[:, 0] - C1 * y[:, None] * g.sh[:, 1] + C1 * z[:, None] * g.sh[:, 2]
           - C1 * x[:, None] * g.sh[:, 3] + 0.5)
    assert np.allclose(out.colors, np.maximum(rgb, 0), rtol=1e-13, atol=1e-15)


# ------------------------------------------------------------------------------------------
# RAS-04 / PRF-05 alpha threshold and cap; RAS-03 power > 0
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_alpha_threshold_1_over_255(profile):
    """RAS-04: alpha < 1/255 is skipped, alpha == 1/255 and above is blended."""
    below = np.nextafter(ALPHA_MIN, 0)
    for o, blended in [(below, False), (ALPHA_MIN, True), (np.nextafter(ALPHA_MIN, 1), True)]:
        out, _, _ = pixel_stack([o], profile)
        assert (out["n_contrib"][8, 8] == 1) == blended
        assert out["alpha"][8, 8] == (pytest.approx(o, rel=1e-15) if blended else 0.0)
    # through the whole pipeline (opacity through the sigmoid, 1e-9 away from the threshold)
    cam = identity_camera(cx=W / 2 + 0.5, cy=H / 2 + 0.5)        # axis on a pixel centre
    for o, blended in [(ALPHA_MIN * (1 - 1e-9), False), (ALPHA_MIN * (1 + 1e-9), True)]:
        g = gaussians_at([[0.0, 0.0, 2.0]], 0.1, logits=logit(o))
        out = render(g, cam, RenderConfig(profile=profile, background=(0.2, 0.4, 0.6)))
        assert (out.n_contrib.max() == 1) == blended
        if not blended:
            assert np.all(out.image == np.array([0.2, 0.4, 0.6])) and np.all(out.alpha == 0)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_alpha_cap(profile):
    """RAS-04/PRF-05: alpha = min(cap, o G): 0.99 (inria) or 0.999 (gsplat)."""
    cap = refgs.get_profile(profile).alpha_max
    for o in (0.995, 0.9995, 1.0):
        out, _, _ = pixel_stack([o], profile, colors=[[1.0, 1.0, 1.0]])
        expected = min(cap, o)
        assert out["image"][8, 8, 0] == pytest.approx(expected, rel=1e-15)
        assert out["final_T"][8, 8] == pytest.approx(1 - expected, rel=1e-12)


def test_power_positive_skipped():
    """RAS-03: a fragment with power > 0 (only possible for an indefinite conic) is skipped."""
    g2d = {"means2d": np.array([[8.5, 8.5]]), "conics": np.array([[1.0, 3.0, 1.0]]),
           "opacities": np.array([0.5]), "colors": np.ones((1, 3)), "depths": np.ones(1)}
    lists = refgs.build_tile_lists(np.array([[0, 1, 0, 1]]), g2d["depths"], np.ones(1, bool), 16, 16)
    out = refgs.composite(g2d, lists, 16, 16, INRIA, np.zeros(3))
    # pixel (9, 7): dx = 1, dy = -1, power = -0.5 (1 + 1) + 3 = 2 > 0
    assert out["n_contrib"][9, 7] == 0 and out["alpha"][9, 7] == 0
    # pixel (9, 9): dx = dy = -1, power = -1 - 3 = -4 <= 0: blended with alpha 0.5 e^-4
    assert out["alpha"][9, 9] == pytest.approx(0.5 * math.exp(-4.0), rel=1e-14)
    assert out["alpha"][8, 8] == 0.5


# ------------------------------------------------------------------------------------------
# RAS-05 / PRF-06 transmittance stop
# ------------------------------------------------------------------------------------------

def _exact_stop_alphas():
    """Alphas (a1, 0.9, 0.9, a4) with T (1 - a4) == 1e-4 exactly in float64 (found by search)."""
    ulp = 2.0 ** -53
    for a1 in 0.9 + np.arange(-20000, 20000) * 2.0 ** -40:
        T3 = np.cumprod(np.array([1.0, 1 - a1, 1 - 0.9, 1 - 0.9]))[-1]
        k0 = round(T_MIN / (T3 * ulp))
        for k in (k0 - 1, k0, k0 + 1):
            a4 = 1 - k * ulp
            if np.cumprod(np.array([1.0, 1 - a1, 1 - 0.9, 1 - 0.9, 1 - a4]))[-1] == T_MIN:
                return [float(a1), 0.9, 0.9, float(a4)]
    raise AssertionError("no exact stack found")


def test_transmittance_stop_exact_equality():
    """RAS-05/PRF-06: at T (1 - a) == 1e-4 exactly, inria ('<') blends, gsplat ('<=') stops;
    the stopping Gaussian is never blended."""
    alphas = _exact_stop_alphas()
    out_i, _, _ = pixel_stack(alphas, "inria")
    out_g, _, _ = pixel_stack(alphas, "gsplat")
    assert out_i["n_contrib"][8, 8] == 4 and out_i["final_T"][8, 8] == T_MIN
    assert out_g["n_contrib"][8, 8] == 3 and out_g["final_T"][8, 8] > T_MIN
    assert out_g["final_T"][8, 8] == np.cumprod([1.0, 1 - alphas[0], 1 - 0.9, 1 - 0.9])[-1]


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_transmittance_stop_just_below_above(profile):
    """RAS-05: test_T just below 1e-4 stops (that Gaussian and everything behind not blended),
    just above blends; full pipeline with the stack on a pixel centre.  A fourth Gaussian
    (alpha 0.5) behind would take T below 1e-4 in either case and is never blended."""
    cam = identity_camera(cx=W / 2 + 0.5, cy=H / 2 + 0.5)
    base = [0.98, 0.98]                             # T = 4e-4 after two
    for rel, blended in [(1 - 1e-6, False), (1 + 1e-6, True)]:
        a3 = 1 - 0.25 * rel                          # T (1 - a3) = 1e-4 * rel
        alphas = base + [a3, 0.5]
        g = gaussians_at([[0.0, 0.0, 2.0 + 0.1 * k] for k in range(4)], 0.08,
                         logits=[logit(a) for a in alphas])
        out = render(g, cam, RenderConfig(profile=profile))
        T = out.final_T[16, 24]
        if blended:
            assert out.n_contrib[16, 24] == 3 and T == pytest.approx(1e-4 * rel, rel=1e-9)
        else:
            assert out.n_contrib[16, 24] == 2 and T == pytest.approx(4e-4, rel=1e-9)
        assert T >= T_MIN * 0.5


# ------------------------------------------------------------------------------------------
# API-06 empty and all-culled scenes
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_empty_and_all_culled_scene(profile):
    """API-06/RAS-06: no Gaussians, or all culled: image == background exactly, alpha = depth =
    n_contrib = 0, final_T = 1, zero-row (or zero) per-Gaussian outputs."""
    bg = (0.25, 0.5, 1.0)
    cfg = RenderConfig(profile=profile, background=bg)
    cam = identity_camera()
    out = render(Gaussians.empty(k=4), cam, cfg)
    assert out.image.shape == (H, W, 3) and np.all(out.image == np.array(bg))
    assert np.all(out.alpha == 0) and np.all(out.depth == 0) and np.all(out.n_contrib == 0)
    assert np.all(out.final_T == 1)
    assert out.radii.shape == (0, 2) and out.means2d.shape == (0, 2) and out.conics.shape == (0, 3)
    # all culled: behind the camera, in front but off screen (gsplat culls, inria's rect is empty)
    g = gaussians_at([[0, 0, -2.0], [0, 0, 0.001], [100.0, 0, 2.0]], 0.05)
    out = render(g, cam, cfg)
    assert not np.any(out.visible) and np.all(out.radii == 0)
    assert np.all(out.image == np.array(bg)) and np.all(out.n_contrib == 0)


# ------------------------------------------------------------------------------------------
# RAS-03..RAS-06 against the per-pixel loop
# ------------------------------------------------------------------------------------------

@settings(max_examples=max_examples(20))
@given(scene=scenes(n=(1, 6), logits=(-3.0, 7.0), sigma_px=(0.8, 6.0), offscreen=0.3))
def test_composite_matches_per_pixel_loop(scene):
    """RAS-03..RAS-06: the tiled, vectorised compositing equals a literal per-pixel loop written
    from the spec (math.md section 4), image/alpha/depth to 1e-12 and n_contrib exactly."""
    out = scene.render()
    ref = composite_loop_of(out)
    assert np.array_equal(out.n_contrib, ref["n_contrib"])
    for name in ("image", "alpha", "depth", "final_T"):
        assert np.allclose(getattr(out, name), ref[name], rtol=0, atol=1e-12), name


@settings(max_examples=max_examples(8))
@given(scene=scenes(n=(2, 5), logits=(-2.0, 6.0), sigma_px=(0.8, 6.0), offscreen=0.2,
                    width=(16, 24), height=(12, 20)))
def test_composite_matches_per_pixel_loop_float32(scene):
    """CNV-11 with RAS-03..RAS-06: in float32 the compositing is the per-pixel loop evaluated in
    float32 arithmetic (also for strongly anisotropic Gaussians, where the float32 rounding of the
    power is largest): n_contrib exactly, image/alpha to float32 rounding."""
    g = scene.gaussians
    rng = np.random.default_rng(scene.seed)
    g = g.replace(log_scales=g.log_scales + rng.uniform(-2.0, 2.0, g.log_scales.shape))
    out = scene.render(g.astype(np.float32))
    ref = composite_loop_of(out)
    assert np.array_equal(out.n_contrib, ref["n_contrib"])
    for name in ("image", "alpha", "depth", "final_T"):
        assert getattr(out, name).dtype == np.float32
        assert np.allclose(getattr(out, name), ref[name], rtol=1e-5, atol=1e-6), name


def test_composite_loop_sees_stops():
    """RAS-05 guard for the property above: its scene range does produce stops."""
    rng = np.random.default_rng(3)
    cam = make_camera(rng, 32, 24)
    g = place_gaussians(rng, cam, 8, logits=(6.0, 7.0), sigma_px=(4.0, 6.0), offscreen=0.0)
    out = render(g, cam)
    ref = composite_loop_of(out)
    assert np.array_equal(out.n_contrib, ref["n_contrib"])
    assert out.final_T.min() < 1e-3 and ref["t_stop"] < 3


# ------------------------------------------------------------------------------------------
# RAS-01 / PRF-08 tile coverage is part of the model
# ------------------------------------------------------------------------------------------

def test_tile_coverage_inria():
    """RAS-01/PRF-08: a pixel in a covered tile is evaluated beyond 3 sigma; a pixel just outside
    the covered tiles is not, even where alpha would exceed 1/255."""
    # dilated variance 6: (f s / z)^2 = 5.7; mean on the centre of pixel (8, 8)
    z = 2.0
    s = math.sqrt(5.7) * z / F
    cam = identity_camera(cx=8.5, cy=8.5)
    g = gaussians_at([[0.0, 0.0, z]], s, logits=logit(0.99))
    out = render(g, cam, RenderConfig(profile="inria"))
    var = out.cov2d[0, 0]
    assert var == pytest.approx(6.0, rel=1e-12)
    r = out.radii[0, 0]
    assert r == math.ceil(3 * math.sqrt(6.0 + math.sqrt(0.1))) == 8
    assert out.cache["proj"]["tile_rect"][0].tolist() == [0, 1, 0, 1]
    sigma = math.sqrt(var)
    # pixel (8, 0): dx = 8 > 3 sigma = 7.35, inside tile 0: blended with alpha 0.99 e^{-32/6}
    assert 8 > 3 * sigma
    assert out.alpha[8, 0] == pytest.approx(0.99 * math.exp(-0.5 * 64 / var), rel=1e-12)
    assert out.alpha[8, 0] > ALPHA_MIN
    # pixel (8, 16): also dx = 8, same alpha in the continuum, but tile 1 is not covered
    assert out.alpha[8, 16] == 0 and out.n_contrib[8, 16] == 0


def test_tile_coverage_gsplat():
    """RAS-01/PRF-08 gsplat: the per-axis, opacity-aware box; a pixel of a covered tile beyond
    3 sigma is evaluated."""
    z = 2.0
    s = math.sqrt(4.0 - 0.3) * z / F                     # dilated variance 4
    cam = identity_camera(cx=8.5, cy=8.5)
    g = gaussians_at([[0.0, 0.0, z]], s, logits=logit(0.99))
    out = render(g, cam, RenderConfig(profile="gsplat"))
    ext = min(3.33, math.sqrt(2 * math.log(0.99 * 255)))
    assert out.radii[0].tolist() == [math.ceil(ext * 2.0)] * 2 == [7, 7]
    assert out.cache["proj"]["tile_rect"][0].tolist() == [0, 1, 0, 1]
    # pixel (6, 2): (dx, dy) = (6, 2), Mahalanobis sqrt(10) = 3.16 sigma (> 3 sigma), inside
    # the box (|dx| <= 7) and tile 0: blended, alpha 0.99 e^-5 > 1/255
    assert out.alpha[6, 2] == pytest.approx(0.99 * math.exp(-5.0), rel=1e-12)
    assert out.n_contrib[6, 2] == 1


@settings(max_examples=max_examples(15))
@given(scene=scenes(n=(1, 5), sigma_px=(0.5, 8.0), offscreen=0.5, logits=(-6.0, 5.0)))
def test_radii_and_tile_rect_rules(scene):
    """PRJ-05/PRF-04/PRF-08: radii and tile rectangles recomputed from the 2D covariance."""
    out = scene.render()
    prof = out.cache["profile"]
    a, b, c = out.cov2d.T
    W_, H_ = scene.camera.width, scene.camera.height
    gx, gy = -(-W_ // TILE_SIZE), -(-H_ // TILE_SIZE)
    vis = out.visible
    m = out.means2d
    if prof.name == "inria":
        mid = (a + c) / 2
        r = np.ceil(3 * np.sqrt(mid + np.sqrt(np.maximum(0.1, mid * mid - (a * c - b * b)))))
        rx = ry = r
        px, py = m[:, 0] - 0.5, m[:, 1] - 0.5
        rect = [np.trunc((px - rx) / 16), np.trunc((px + rx + 15) / 16),
                np.trunc((py - ry) / 16), np.trunc((py + ry + 15) / 16)]
        assert np.array_equal(out.radii[:, 0], out.radii[:, 1])
    else:
        o = out.opacities
        with np.errstate(divide="ignore", invalid="ignore"):
            ext = np.minimum(3.33, np.sqrt(2 * np.log(o * 255)))
        rx, ry = np.ceil(ext * np.sqrt(a)), np.ceil(ext * np.sqrt(c))
        rect = [np.floor((m[:, 0] - rx) / 16), np.ceil((m[:, 0] + rx) / 16),
                np.floor((m[:, 1] - ry) / 16), np.ceil((m[:, 1] + ry) / 16)]
        assert np.all(~vis | (o >= ALPHA_MIN))
        on_screen = (m[:, 0] + rx > 0) & (m[:, 0] - rx < W_) & (m[:, 1] + ry > 0) & (m[:, 1] - ry < H_)
        assert np.all(~vis | on_screen)
    assert np.array_equal(out.radii[vis], np.stack([rx, ry], -1)[vis].astype(int))
    assert np.all(out.radii[~vis] == 0)
    lim = [gx, gx, gy, gy]
    rect = np.stack([np.clip(x, 0, L) for x, L in zip(rect, lim)], -1)
    assert np.array_equal(out.cache["proj"]["tile_rect"][vis], rect[vis].astype(int))
    assert np.all((rect[vis, 1] > rect[vis, 0]) & (rect[vis, 3] > rect[vis, 2]))


def test_radius_floor_and_opacity_aware():
    """PRF-04: inria's 0.1 eigenvalue floor (isotropic: lambda = a + sqrt(0.1)); gsplat's extend
    min(3.33, sqrt(2 ln(255 o))) and its cull at o < 1/255."""
    z = 2.0
    cam = identity_camera()
    s = math.sqrt(4.9) * z / F                       # (f s / z)^2 = 4.9, a = c = 5.2
    g = gaussians_at([[0, 0, z]] * 3, s, logits=[logit(0.9), logit(0.02), logit(0.003)])
    oi = render(g, cam, RenderConfig(profile="inria"))
    assert oi.cov2d[0] == pytest.approx([5.2, 0.0, 5.2], rel=1e-13, abs=1e-13)
    # the floor decides here: ceil(3 sqrt(5.2 + sqrt(0.1))) = 8, without it 7
    assert oi.radii[0].tolist() == [math.ceil(3 * math.sqrt(5.2 + math.sqrt(0.1)))] * 2 == [8, 8]
    assert math.ceil(3 * math.sqrt(5.2 + math.sqrt(0.01))) == 7
    og = render(g, cam, RenderConfig(profile="gsplat"))
    ext = min(3.33, math.sqrt(2 * math.log(0.9 * 255)))
    assert og.radii[0].tolist() == [math.ceil(ext * math.sqrt(5.2))] * 2
    ext = math.sqrt(2 * math.log(0.02 * 255))
    assert og.radii[1].tolist() == [math.ceil(ext * math.sqrt(5.2))] * 2 == [5, 5]
    assert og.radii[2].tolist() == [0, 0] and not og.visible[2]
    assert oi.visible[2]                              # inria has no opacity cull


# ------------------------------------------------------------------------------------------
# RAS-02 sort by depth, ties by index
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_depth_sort_ties_by_index(profile):
    """RAS-02: front to back by camera depth; equal depths keep the Gaussian index order."""
    cam = identity_camera(cx=W / 2 + 0.5, cy=H / 2 + 0.5)
    red, green = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    o = 0.6
    for z0, z1, front in [(2.0, 2.0, 0), (2.5, 2.0, 1), (2.0, 2.5, 0)]:
        g = gaussians_at([[0, 0, z0], [0, 0, z1]], [0.1, 0.1, 0.1], logits=logit(o),
                         rgb=[red, green])
        px = render(g, cam, RenderConfig(profile=profile)).image[16, 24]
        first = (red, green)[front]
        second = (red, green)[1 - front]
        expected = np.array(first) * o + np.array(second) * o * (1 - o)
        assert np.allclose(px, expected, rtol=1e-13), (z0, z1)
    lists = refgs.build_tile_lists(np.tile([0, 1, 0, 1], (4, 1)), np.array([3.0, 1.0, 3.0, 1.0]),
                                   np.ones(4, bool), 16, 16)
    assert lists["gauss"].tolist() == [1, 3, 0, 2]


# ------------------------------------------------------------------------------------------
# SH-01 extra coefficients
# ------------------------------------------------------------------------------------------

def test_sh_extra_coefficients_ignored():
    """SH-01: coefficients beyond the active degree change nothing and receive zero gradient;
    the default degree is min(3, floor(sqrt(K)) - 1)."""
    rng = np.random.default_rng(12)
    cam = make_camera(rng, 32, 24)
    g16 = place_gaussians(rng, cam, 4, sh_degree=3, sh_spread=0.3)
    g4 = g16.replace(sh=g16.sh[:, :4].copy())
    cfg = RenderConfig(sh_degree=1)
    o16, o4 = render(g16, cam, cfg), render(g4, cam, cfg)
    assert np.array_equal(o16.image, o4.image)
    noisy = g16.sh.copy()
    noisy[:, 4:] += rng.normal(size=noisy[:, 4:].shape)
    assert np.array_equal(render(g16.replace(sh=noisy), cam, cfg).image, o16.image)
    gr = render_backward(o16, rng.normal(size=(24, 32, 3)))
    assert np.all(gr.sh[:, 4:] == 0) and np.any(gr.sh[:, :4] != 0)
    for k, deg in [(1, 0), (3, 0), (4, 1), (8, 1), (9, 2), (15, 2), (16, 3), (25, 3)]:
        assert RenderConfig().active_sh_degree(k) == deg
    # the default for K = 16 is degree 3, which differs from degree 1
    assert not np.allclose(render(g16, cam).image, o16.image)


# ------------------------------------------------------------------------------------------
# RAS-09 chunked evaluation
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("chunk_tiles", [1, 3])
def test_chunked_matches_unchunked(monkeypatch, profile, chunk_tiles):
    """RAS-09: with CHUNK_PAIRS so small that one long tile list is split into segments (T and
    the stop carried across them) and tiles are batched differently, forward and backward equal
    the unchunked results."""
    rng = np.random.default_rng(13)
    cam = identity_camera(fx=40.0, cx=24.0, cy=16.0)
    # 11 Gaussians inside tile 0 (a long list with an opaque middle that stops some pixels),
    # plus a few spread over the image
    n0 = 11
    u = rng.uniform(6, 10, n0)
    v = rng.uniform(6, 10, n0)
    z = rng.uniform(2, 4, n0)
    t0 = np.stack([(u - 24) * z / 40, (v - 16) * z / 40, z], -1)
    t1 = np.stack([rng.uniform(-0.6, 0.6, 5), rng.uniform(-0.4, 0.4, 5), rng.uniform(2, 4, 5)], -1)
    means = np.concatenate([t0, t1])
    n = means.shape[0]
    scales = np.concatenate([1.6 * t0[:, 2:] / 40 * rng.uniform(0.7, 1.3, (n0, 3)),
                             0.15 * rng.uniform(0.5, 1.5, (5, 3))])
    logits = np.concatenate([rng.uniform(3, 7, n0), rng.uniform(-1, 2, 5)])
    sh = 0.3 * rng.normal(size=(n, 4, 3))
    g = Gaussians(means, np.log(scales), rng.normal(size=(n, 4)), logits, sh)
    cfg = RenderConfig(profile=profile, background=(0.3, 0.1, 0.7))
    ref = render(g, cam, cfg)
    lengths = np.diff(ref.cache["lists"]["offsets"])
    cot = (rng.normal(size=(H, W, 3)), rng.normal(size=(H, W)), rng.normal(size=(H, W)))
    gref = render_backward(ref, *cot)
    pairs = chunk_tiles * rasterize.PIX
    monkeypatch.setattr(rasterize, "CHUNK_PAIRS", pairs)
    assert lengths.max() > pairs // rasterize.PIX          # the long list is segmented
    batches = list(rasterize._batches(lengths))
    assert any(s0 > 0 for _, s0, _, _ in batches)
    out = render(g, cam, cfg)
    assert ref.final_T.min() < 1e-3                         # a stop happens in the long list
    # decisions and transmittance do not depend on the chunk size at all; sums only through
    # floating-point reassociation
    assert np.array_equal(out.n_contrib, ref.n_contrib)
    assert np.array_equal(out.final_T, ref.final_T) and np.array_equal(out.alpha, ref.alpha)
    for name in ("image", "depth"):
        assert np.allclose(getattr(out, name), getattr(ref, name), rtol=1e-13, atol=1e-15), name
    gr = render_backward(out, *cot)
    for name, arr in gr.to_dict().items():
        other = getattr(gref, name)
        assert np.max(np.abs(other)) > 1e-6, name
        assert np.allclose(arr, other, rtol=1e-11, atol=1e-13 * np.max(np.abs(other))), name


def test_pixel_tile_lists_helper_agrees():
    """RAS-01/RAS-02 guard: the test's own tile lists equal refgs' (so the loop comparison is
    meaningful)."""
    rng = np.random.default_rng(14)
    cam = make_camera(rng, 40, 32)
    g = place_gaussians(rng, cam, 6, sigma_px=(1.0, 9.0), offscreen=0.3)
    for profile in ("inria", "gsplat"):
        out = render(g, cam, RenderConfig(profile=profile))
        mine = pixel_tile_lists(out.cache["proj"]["tile_rect"], out.visible, out.depths, 40, 32)
        lists = out.cache["lists"]
        gx = 3
        for (tx, ty), members in mine.items():
            t = ty * gx + tx
            assert lists["gauss"][lists["offsets"][t]:lists["offsets"][t + 1]].tolist() == members
