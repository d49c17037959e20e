"""Hand-derived gradients against central finite differences in float64 (COV-02, PRJ-07, PRJ-08,
SH-04, RAS-07, RAS-08, RAS-10, API-05).

Every check uses :func:`strategies.assert_grad_close`: relative error <= 1e-6 in the field-wise
norm (|an - fd| <= 1e-6 max|fd|) and element-wise where |fd| >= 1e-3 max|fd|; differences are
Richardson-extrapolated central differences with step ``FD_STEP``.  Random scenes are drawn away
from every discontinuity of the model by the margin filter of tests/strategies.py.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings

import refgs
from refgs import RenderConfig, render_backward
from refgs.projection import frustum_limits

from strategies import (FD_STEP, FD_STEP_SMOOTH, MARGIN, Scene, assert_grad_close, far_from_thresholds,
                        fd_gradient, fd_noise_floor, inria_dL_dconic, inria_dL_dcov2d, make_camera, max_examples,
                        place_gaussians, random_cotangents, render_fd_check, scenes)

#: Examples per profile for the whole-render check (each costs ~1 s: ~40 coordinates x 4 renders).
RENDER_EXAMPLES = 10


# ------------------------------------------------------------------------------------------
# Stage by stage
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_covariance_3d_backward_fd(seed):
    """COV-02: d <V, Sigma(q, log s)> / d(q, log s) for unnormalised q and a non-symmetric V."""
    rng = np.random.default_rng(seed)
    n = 4
    q = rng.normal(size=(n, 4)) * rng.uniform(0.3, 3.0, (n, 1))
    ls = rng.uniform(-2.0, 0.5, (n, 3))
    V = rng.normal(size=(n, 3, 3))
    v_q, v_ls = refgs.covariance_3d_backward(refgs.covariance_3d(q, ls), V)
    fq = fd_gradient(lambda x: float(np.sum(V * refgs.covariance_3d(x, ls)["cov3d"])), q,
                     h=FD_STEP_SMOOTH)
    fl = fd_gradient(lambda x: float(np.sum(V * refgs.covariance_3d(q, x)["cov3d"])), ls,
                     h=FD_STEP_SMOOTH)
    assert_grad_close(v_q, fq, "d/dquats")
    assert_grad_close(v_ls, fl, "d/dlog_scales")


def _projection_inputs(rng, profile, antialiased, n=6):
    """Gaussians around and beyond the frustum edges, kept away from the clamp boundary, at least
    one of them clamped and still visible (its footprint reaches the image)."""
    cam = make_camera(rng, 32, 24)
    prof = refgs.get_profile(profile)
    lims = frustum_limits(cam, prof, np.dtype(np.float64))
    o = np.full(n, 0.9)
    for _ in range(200):
        g = place_gaussians(rng, cam, n, offscreen=0.6, sigma_px=(2.0, 10.0))
        t = refgs.world_to_camera(g.means, cam.world_to_camera)
        u, v = t[:, 0] / t[:, 2], t[:, 1] / t[:, 2]
        gaps = np.concatenate([u + lims[0], u - lims[1], v + lims[2], v - lims[3]])
        cov = refgs.covariance_3d(g.quats, g.log_scales)["cov3d"]
        fwd = refgs.project_gaussians(g.means, cov, o, cam, prof, antialiased=antialiased)
        clamped = fwd["clamped_x"] | fwd["clamped_y"]
        if np.min(np.abs(gaps)) > MARGIN and np.any(clamped & fwd["visible"]):
            return cam, prof, g, cov, o, fwd
    raise AssertionError("no suitable draw")


@pytest.mark.parametrize("profile,antialiased", [("inria", False), ("gsplat", False), ("gsplat", True)])
@pytest.mark.parametrize("seed", range(3))
def test_project_gaussians_backward_fd(profile, antialiased, seed):
    """PRJ-07/PRJ-08: means2d, conics (off-diagonal once), depths and the compensation w.r.t. the
    3D mean and the 3D covariance entries, including clamped (off-screen) Gaussians."""
    rng = np.random.default_rng(100 + seed)
    cam, prof, g, cov, o, fwd = _projection_inputs(rng, profile, antialiased)
    n = len(g)
    vm, vc, vz = rng.normal(size=(n, 2)), rng.normal(size=(n, 3)), rng.normal(size=n)
    vcomp = rng.normal(size=n) if antialiased else None

    def loss(means, cov3d):
        f = refgs.project_gaussians(means, cov3d, o, cam, prof, antialiased=antialiased)
        keep = fwd["visible"]                      # the backward zeroes culled rows
        L = np.sum(vm[keep] * f["means2d"][keep]) + np.sum(vc[keep] * f["conics"][keep]) \
            + np.sum(vz[keep] * f["depths"][keep])
        if antialiased:
            L += np.sum(vcomp[keep] * f["comp"][keep])
        return float(L)
    v_means, v_cov = refgs.project_gaussians_backward(fwd, cam, vm, vc, vz, vcomp)
    # the step moves t.x / t.z by at most ~2 FD_STEP_SMOOTH / z < MARGIN: no clamp flips
    assert_grad_close(v_means, fd_gradient(lambda x: loss(x, cov), g.means, h=FD_STEP_SMOOTH),
                      "d/dmeans")
    assert_grad_close(v_cov, fd_gradient(lambda x: loss(g.means, x), cov, h=FD_STEP_SMOOTH),
                      "d/dcov3d")
    assert np.all(v_means[~fwd["visible"]] == 0) and np.all(v_cov[~fwd["visible"]] == 0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_eval_sh_colors_backward_fd(degree):
    """SH-04: colour gradient w.r.t. every active coefficient and w.r.t. the mean (view direction);
    channels clamped at 0 pass nothing."""
    rng = np.random.default_rng(200 + degree)
    n, k = 6, 16
    means = rng.normal(size=(n, 3)) * 2
    campos = rng.normal(size=3)
    sh = rng.normal(size=(n, k, 3)) * 0.4
    sh[:, 0] += rng.uniform(-4.0, 4.0, (n, 3))            # some channels clamped
    fwd = refgs.eval_sh_colors(means, sh, campos, degree)
    nb = (degree + 1) ** 2
    rgb = np.einsum("nk,nkc->nc", fwd["basis"], sh[:, :nb]) + 0.5
    assert np.min(np.abs(rgb)) > MARGIN and np.any(fwd["clamped"]) and not np.all(fwd["clamped"])
    V = rng.normal(size=(n, 3))
    v_sh, v_means = refgs.eval_sh_colors_backward(fwd, sh, V)

    def loss(m, s):
        return float(np.sum(V * refgs.eval_sh_colors(m, s, campos, degree)["colors"]))
    assert_grad_close(v_sh, fd_gradient(lambda x: loss(means, x), sh, h=FD_STEP_SMOOTH), "d/dsh")
    assert_grad_close(v_means, fd_gradient(lambda x: loss(x, sh), means, h=FD_STEP_SMOOTH),
                      "d/dmeans")
    assert np.all(v_sh[:, nb:] == 0)
    assert np.all(v_sh[fwd["clamped"][:, None, :].repeat(k, 1)] == 0)


@settings(max_examples=max_examples(10))
@given(scene=scenes(n=(1, 4), sigma_px=(1.2, 4.0), logits=(-1.0, 4.0), offscreen=0.2))
def test_composite_backward_fd(scene):
    """RAS-07/RAS-08/RAS-10: d L / d(means2d, conics, opacities, colours, depths) of the
    compositing with fixed tile lists; random v_image, v_alpha, v_depth and background."""
    out = scene.render()
    assume(out.visible.any() and far_from_thresholds(out))
    prof = out.cache["profile"]
    g2d, lists = out.cache["g2d"], out.cache["lists"]
    W, H = scene.camera.width, scene.camera.height
    bg = np.asarray(scene.config.background, float)
    cot = random_cotangents(np.random.default_rng(scene.seed), H, W)
    grads = refgs.composite_backward(g2d, lists, W, H, prof, bg, out.final_T, cot["v_image"],
                                     cot["v_alpha"], cot["v_depth"])
    vis = out.visible

    def loss(name, x):
        c = refgs.composite(dict(g2d, **{name: x}), lists, W, H, prof, bg)
        return float(np.sum(cot["v_image"] * c["image"]) + np.sum(cot["v_alpha"] * c["alpha"])
                     + np.sum(cot["v_depth"] * c["depth"]))
    # A step h in a conic entry moves the power by up to h dx^2 / 2, which on the 1/255 ring is
    # ln(255 o) max(a, c) h (hundreds of times h for the larger splats): the conic step is scaled
    # so that the stencil (+-2h) moves no fragment by more than MARGIN / 10 (strategies.py).
    ring2 = 2 * np.log(255 * np.maximum(out.opacities[vis], 1 / 255)) * out.cov2d[vis][:, [0, 2]].max(1)
    h_conic = min(FD_STEP, 0.1 * MARGIN / (2 * 0.5 * float(ring2.max())))
    # colours and depths enter linearly (the lists are fixed): a large step has no truncation
    # error and little rounding noise
    for name, key, h in [("means2d", "v_means2d", FD_STEP), ("conics", "v_conics", h_conic),
                         ("opacities", "v_opacities", FD_STEP), ("colors", "v_colors", 1e-2),
                         ("depths", "v_depths", 1e-2)]:
        x = g2d[name]
        idx = [i for i in np.ndindex(x.shape) if vis[i[0]]]
        fd = fd_gradient(lambda xx, name=name: loss(name, xx), x, idx, h=h)
        assert_grad_close(grads[key], fd, f"d/d{name}", atol=fd_noise_floor(out, cot, h))


# ------------------------------------------------------------------------------------------
# The whole render
# ------------------------------------------------------------------------------------------

@settings(max_examples=max_examples(RENDER_EXAMPLES))
@given(scene=scenes(profiles=("inria",), n=(1, 3), width=(16, 32), height=(12, 24)))
def test_render_backward_fd_inria(scene):
    """API-05: every raw parameter through render_backward, inria profile, random background,
    opacity_scale sometimes, v_image + v_alpha + v_depth."""
    out = scene.render()
    assume(out.visible.any() and far_from_thresholds(out))
    rng = np.random.default_rng(scene.seed)
    render_fd_check(scene, random_cotangents(rng, scene.camera.height, scene.camera.width), rng=rng)


@settings(max_examples=max_examples(RENDER_EXAMPLES))
@given(scene=scenes(profiles=("gsplat",), n=(1, 3), width=(16, 32), height=(12, 24)))
def test_render_backward_fd_gsplat(scene):
    """API-05, gsplat profile: antialiased mode and opacity_scale drawn at random."""
    out = scene.render()
    assume(out.visible.any() and far_from_thresholds(out))
    rng = np.random.default_rng(scene.seed)
    render_fd_check(scene, random_cotangents(rng, scene.camera.height, scene.camera.width), rng=rng)


def _fixed_scene(profile, seed, **cfg):
    rng = np.random.default_rng(seed)
    cam = make_camera(rng, 24, 16)
    for _ in range(50):
        g = place_gaussians(rng, cam, 3, sh_degree=1, offscreen=0.0)
        scene = Scene(g, cam, RenderConfig(profile=profile, **cfg), seed)
        out = scene.render()
        if out.visible.all() and far_from_thresholds(out):
            return scene, rng
    raise AssertionError("no scene away from the thresholds")


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("path", ["alpha", "depth"])
def test_alpha_and_depth_paths_fd(profile, path):
    """RAS-06/RAS-07: the v_alpha and v_depth cotangents alone (v_image = 0)."""
    scene, rng = _fixed_scene(profile, 31, background=(0.4, 0.2, 0.9))
    H, W = scene.camera.height, scene.camera.width
    cot = {"v_image": np.zeros((H, W, 3)), "v_alpha": None, "v_depth": None}
    cot["v_" + path] = rng.normal(size=(H, W))
    g = render_backward(scene.render(), **cot)
    assert np.any(g.means != 0) and np.all(g.sh == 0)
    render_fd_check(scene, cot, rng=rng, fields=("means", "log_scales", "quats", "opacity_logits"))


@pytest.mark.parametrize("option", ["antialiased", "opacity_scale", "both"])
def test_gsplat_options_fd(option):
    """PRJ-08 antialiased compensation and API-02 opacity_scale through the whole render."""
    cfg = {"antialiased": option in ("antialiased", "both")}
    if option in ("opacity_scale", "both"):
        cfg["opacity_scale"] = np.array([0.7, 1.3, 1.05])
    scene, rng = _fixed_scene("gsplat", 47, background=(0.1, 0.8, 0.3), **cfg)
    H, W = scene.camera.height, scene.camera.width
    render_fd_check(scene, random_cotangents(rng, H, W), rng=rng)


# ------------------------------------------------------------------------------------------
# RAS-10 the alpha cap, per profile
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_alpha_cap_gradient_per_profile(profile):
    """RAS-10/PRF-07: one fragment with o G above the cap: inria passes dL/dalpha to o and G as if
    alpha = o G; gsplat passes nothing (the exact derivative of min(cap, o G))."""
    prof = refgs.get_profile(profile)
    o = 0.9995
    c = np.array([0.2, 0.7, 0.4])
    bg = np.array([0.5, 0.1, 0.3])
    g2d = {"means2d": np.array([[8.5, 8.5]]), "conics": np.array([[0.5, 0.0, 0.5]]),
           "opacities": np.array([o]), "colors": c[None], "depths": np.array([2.0])}
    lists = refgs.build_tile_lists(np.array([[0, 1, 0, 1]]), g2d["depths"], np.ones(1, bool), 16, 16)
    out = refgs.composite(g2d, lists, 16, 16, prof, bg)
    v = np.zeros((16, 16, 3))
    v[8, 8] = [1.0, -2.0, 0.5]                       # only the centre pixel (G = 1 there)
    gr = refgs.composite_backward(g2d, lists, 16, 16, prof, bg, out["final_T"], v, None, None)
    assert out["alpha"][8, 8] == pytest.approx(prof.alpha_max, rel=1e-15)
    dL_dalpha = float(v[8, 8] @ (c - bg))
    if prof.grad_through_alpha_cap:
        assert gr["v_opacities"][0] == pytest.approx(dL_dalpha * 1.0, rel=1e-14)
    else:
        assert gr["v_opacities"][0] == 0.0
        h = 1e-6
        fd = [(refgs.composite(dict(g2d, opacities=np.array([o + s * h])), lists, 16, 16, prof, bg)
               ["image"][8, 8] @ v[8, 8]) for s in (1, -1)]
        assert (fd[0] - fd[1]) / (2 * h) == 0.0
    # the colour gradient is alpha T v in both profiles
    assert gr["v_colors"][0] == pytest.approx(prof.alpha_max * v[8, 8], rel=1e-14)


# ------------------------------------------------------------------------------------------
# RAS-08 the original's -0.5 convention on the conic off-diagonal (peers.md 5, item 3)
# ------------------------------------------------------------------------------------------

def _single_gaussian_scene():
    """One anisotropic, rotated Gaussian, every fragment below the cap and away from 1/255."""
    scene, rng = _fixed_scene("inria", 5, background=(0.3, 0.3, 0.3))
    g = scene.gaussians.subset(np.array([0]))
    scene = Scene(g, scene.camera, scene.config, scene.seed)
    out = scene.render()
    assert far_from_thresholds(out) and out.visible[0]
    return scene, out, rng


def test_inria_conic_convention_equals_chain_and_fd():
    """RAS-08: the original's per-entry convention (dL/dconic.y = -0.5 G dx dy dL/dG) followed by
    computeCov2D's factor 2 in dL/db gives the same dL/d(a, b, c) -- and the same dL/dSigma3D --
    as refgs' "off-diagonal once" chain, and both equal finite differences."""
    scene, out, rng = _single_gaussian_scene()
    cam = scene.camera
    H, W = cam.height, cam.width
    v = rng.normal(size=(H, W, 3))
    # per fragment: L = sum v . (c a + (1 - a) bg), a = o G (one Gaussian, below the cap)
    m = out.means2d[0]
    A, B, C = out.conics[0]
    o = out.opacities[0]
    col = out.colors[0]
    bg = np.asarray(scene.config.background)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dx, dy = m[0] - jj, m[1] - ii
    G = np.exp(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)
    blended = out.n_contrib == 1
    dL_dG = np.where(blended, o * np.einsum("hwc,c->hw", v, col - bg), 0.0)
    gx, gy, gw = (np.sum(x) for x in inria_dL_dconic(dx, dy, G, dL_dG))
    a, b, c = out.cov2d[0]
    da, db, dc = inria_dL_dcov2d(a, b, c, gx, gy, gw)

    # (1) against finite differences of L in (a, b, c): b moves both symmetric entries
    proj = out.cache["proj"]
    lists = out.cache["lists"]
    prof = out.cache["profile"]

    def loss_abc(abc):
        aa, bb, cc = abc
        det = aa * cc - bb * bb
        g2d = dict(out.cache["g2d"], conics=np.array([[cc / det, -bb / det, aa / det]]))
        return float(np.sum(v * refgs.composite(g2d, lists, W, H, prof, bg)["image"]))
    fd = fd_gradient(loss_abc, np.array([a, b, c]))
    assert_grad_close(np.array([da, db, dc]), fd, "original convention vs FD")
    # the "fix" proposed in the issues (-1 on the off-diagonal, keeping the factor 2) doubles dL/db
    _, db_wrong, _ = inria_dL_dcov2d(a, b, c, gx, 2 * gy, gw)
    assert abs(db_wrong - fd[1]) > 0.5 * abs(fd[1])

    # (2) refgs' chain: composite_backward (dL/dB once) -> project_gaussians_backward -> dL/dSigma3D
    vc = refgs.composite_backward(out.cache["g2d"], lists, W, H, prof, bg, out.final_T, v, None, None)
    assert vc["v_conics"][0, 1] == pytest.approx(2 * gy, rel=1e-10)
    _, v_cov3d = refgs.project_gaussians_backward(proj, cam, np.zeros((1, 2)), vc["v_conics"],
                                                  np.zeros(1))
    # the original's dL/dSigma3D (computeCov2DCUDA): T = J W, diagonal entries
    # T0i^2 da + T0i T1i db + T1i^2 dc, off-diagonal (i < j) 2 T0i T0j da + (T0i T1j + T0j T1i) db
    # + 2 T1i T1j dc -- the gradient w.r.t. the symmetric pair Sigma_ij = Sigma_ji
    T = proj["J"][0] @ cam.rotation
    for i in range(3):
        for j in range(i, 3):
            if i == j:
                orig = T[0, i] ** 2 * da + T[0, i] * T[1, i] * db + T[1, i] ** 2 * dc
                ours = v_cov3d[0, i, i]
            else:
                orig = 2 * T[0, i] * T[0, j] * da + (T[0, i] * T[1, j] + T[0, j] * T[1, i]) * db \
                    + 2 * T[1, i] * T[1, j] * dc
                ours = v_cov3d[0, i, j] + v_cov3d[0, j, i]
            assert ours == pytest.approx(orig, rel=1e-9, abs=1e-12 * abs(da)), (i, j)
