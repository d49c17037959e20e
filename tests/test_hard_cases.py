"""The numerical hard cases HARD-01 .. HARD-13 (peers.md section 5, in that order).

Each test names its case; gradients are checked against finite differences (float64) on scenes
kept away from the model's thresholds by the margin filter of tests/strategies.py.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import refgs
from refgs import Camera, Gaussians, Gradients, RenderConfig, render, render_backward
from refgs.constants import ALPHA_MIN, SH_C0, T_MIN, TILE_SIZE
from refgs.projection import frustum_limits, tile_rectangles

from conftest import data_root
from strategies import (Scene, assert_grad_close, composite_loop_of, far_from_thresholds,
                        fd_gradient, inria_dL_dcov2d, make_camera, place_gaussians,
                        random_cotangents, render_fd_check, scalar_loss, threshold_distances)

W, H = 32, 24
F = 20.0


def identity_camera(fx=F, cx=W / 2, cy=H / 2, width=W, height=H) -> Camera:
    return Camera(np.eye(4), np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]]), width, height)


def make_gaussians(means, log_scales, quats, logits, rgb=None, k=1) -> Gaussians:
    means = np.atleast_2d(np.asarray(means, float))
    n = means.shape[0]
    sh = np.zeros((n, k, 3))
    rgb = np.full((n, 3), 0.7) if rgb is None else np.broadcast_to(np.asarray(rgb, float), (n, 3))
    sh[:, 0] = (rgb - 0.5) / SH_C0
    return Gaussians(means, np.broadcast_to(np.asarray(log_scales, float), (n, 3)).copy(),
                     np.broadcast_to(np.asarray(quats, float), (n, 4)).copy(),
                     np.broadcast_to(np.asarray(logits, float), (n,)).copy(), sh)


def all_finite(*arrays) -> bool:
    return all(np.all(np.isfinite(a)) for a in arrays)


def smooth_scene(build, tweaks) -> tuple[Scene, "refgs.RenderOutput"]:
    """The first ``build(t)`` over ``tweaks`` that is away from every threshold (strategies.py
    margin filter): hand-built scenes stay valid when a harmless parameter shifts a pixel onto a
    threshold band."""
    for t in tweaks:
        scene = build(t)
        out = scene.render()
        if far_from_thresholds(out):
            return scene, out
    raise AssertionError(f"no tweak in {list(tweaks)} gives a scene away from the thresholds: "
                         f"{threshold_distances(out)}")


TWEAKS = np.linspace(0.0, 0.2, 9)


def conic_to_cov2d_grad(cov2d, v_conics):
    """dL/d(a, b, c) of the dilated 2D covariance from dL/d(A, B, C), B counted once
    (conic = (c, -b, a) / (a c - b^2)), derived independently of refgs."""
    a, b, c = cov2d.T
    det = a * c - b * b
    vA, vB, vC = v_conics.T
    d2 = det * det
    va = (-c * c * vA + b * c * vB - b * b * vC) / d2
    vb = (2 * b * c * vA - (det + 2 * b * b) * vB + 2 * a * b * vC) / d2
    vc = (-b * b * vA + a * b * vB - a * a * vC) / d2
    return va, vb, vc


# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard01_frustum_clamp_depth_grad(profile):
    """HARD-01 (diff-gaussian-rasterization #75), PRJ-07: for a Gaussian whose t.x/t.z is beyond
    the clamp, the depth gradient is exact (matches finite differences); the original's
    formula, which keeps the generic 2 fx t.x / t.z^3 term with the clamped t.x, would differ by
    fx u_c / t.z^2 dL/dJ02."""
    cam = identity_camera(cx=15.0, cy=12.5)            # off-centre: gsplat's limits differ
    prof = refgs.get_profile(profile)
    lnx, lpx, lny, lpy = frustum_limits(cam, prof, np.dtype(np.float64))
    z = 2.0
    u_raw = 1.2 * lpx                                  # 1.2x beyond the right limit
    v_raw = -1.25 * lny                                # 1.25x beyond the top limit

    def build(t):
        g = make_gaussians([[u_raw * z, 0.05, z], [0.1 * 2.2, v_raw * 2.2, 2.2], [-0.1, 0.2, 2.5]],
                           [[math.log(0.45), math.log(0.3), math.log(0.6)]] * 3,
                           [[0.9, 0.1, 0.3, -0.2]], [1.1, 1.3, 0.5 + t])
        return Scene(g, cam, RenderConfig(profile=profile, background=(0.2, 0.5, 0.1)))
    scene, out = smooth_scene(build, TWEAKS)
    g = scene.gaussians
    proj = out.cache["proj"]
    assert proj["clamped_x"].tolist() == [True, False, False]
    assert proj["clamped_y"].tolist() == [False, True, False]
    assert out.visible.all()
    rng = np.random.default_rng(1)
    cot = random_cotangents(rng, H, W)
    grads = render_backward(out, **cot)
    fd = fd_gradient(lambda m: scalar_loss(scene.render(g.replace(means=m)), cot), g.means)
    assert_grad_close(grads.means, fd, "d/dmeans")
    # the original's depth term: add fx u_c / tz^2 dL/dJ02 (camera z), mapped to world
    vc = refgs.composite_backward(out.cache["g2d"], out.cache["lists"], W, H, prof,
                                  np.asarray(scene.config.background), out.final_T,
                                  cot["v_image"], cot["v_alpha"], cot["v_depth"])
    va, vb, vcc = conic_to_cov2d_grad(out.cov2d, vc["v_conics"])
    V = np.zeros((3, 2, 2))
    V[:, 0, 0], V[:, 1, 1] = va, vcc
    V[:, 0, 1] = V[:, 1, 0] = 0.5 * vb
    v_J = 2 * V @ proj["J"] @ proj["cov_cam"]
    tz = out.depths
    delta = [F * lpx / tz[0] ** 2 * v_J[0, 0, 2],          # x clamped at +L_x
             F * -lny / tz[1] ** 2 * v_J[1, 1, 2]]         # y clamped at -L_y (fy = fx = F)
    for i in (0, 1):
        original = grads.means[i] + cam.rotation.T @ np.array([0.0, 0.0, delta[i]])
        assert abs(original[2] - fd[i, 2]) > 1e3 * 1e-6 * np.max(np.abs(fd)), i
        assert abs(original[2] - fd[i, 2]) > 1e-3 * abs(fd[i, 2]), i


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard02_offscreen_needles(profile):
    """HARD-02 (gsplat PR #977): needles (one axis 1e3 .. 1e6 times the others) straddling the
    frustum edges (clamped and unclamped sides, several orientations) render finite values and
    FD-consistent gradients."""
    prof = refgs.get_profile(profile)
    checked = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        cam = make_camera(rng, W, H)
        lims = frustum_limits(cam, prof, np.dtype(np.float64))
        n = 3
        side = rng.integers(0, 4, n)
        z = rng.uniform(2.0, 3.5, n)
        f = rng.uniform(0.85, 1.15, n)            # just inside or just outside the limit
        u = np.where(side == 0, f * lims[1], np.where(side == 1, -f * lims[0], rng.uniform(-0.5, 0.5, n)))
        v = np.where(side == 2, f * lims[3], np.where(side == 3, -f * lims[2], rng.uniform(-0.5, 0.5, n)))
        t_cam = np.stack([u * z, v * z, z], -1)
        means = (t_cam - cam.translation) @ cam.rotation
        major = rng.uniform(0.8, 1.5, n)
        ratio = 10.0 ** rng.uniform(3, 6, (n, 2))      # one axis 1e3 .. 1e6 times the others
        ls = np.log(np.concatenate([major[:, None], major[:, None] / ratio], -1))
        g = make_gaussians(means, ls, rng.normal(size=(n, 4)), rng.uniform(0.0, 2.0, n))
        scene = Scene(g, cam, RenderConfig(profile=profile, background=(0.1, 0.2, 0.3)), seed)
        out = scene.render()
        proj = out.cache["proj"]
        clamped_vis = (proj["clamped_x"] | proj["clamped_y"]) & out.visible
        cot = random_cotangents(rng, H, W)
        grads = render_backward(out, **cot)
        assert all_finite(out.image, out.alpha, out.depth, *grads.to_dict().values())
        if not (clamped_vis.any() and far_from_thresholds(out)):
            continue
        render_fd_check(scene, cot, rng=rng, fields=("means", "log_scales", "quats"))
        checked += 1
        if checked == 2:
            break
    assert checked == 2


def test_hard03_conic_offdiag_convention():
    """HARD-03 (gaussian-splatting #551 and many others), RAS-08: refgs' dL/dB counts the
    off-diagonal once and equals the finite difference in B; the original's -0.5 slot is the
    derivative w.r.t. *one* of the two symmetric entries of the conic matrix (half of it), and
    its factor 2 in dL/db restores the same dL/dSigma.  Full chain checked by FD in Sigma3D."""
    rng = np.random.default_rng(3)
    cam = identity_camera()
    scene, out = smooth_scene(lambda t: Scene(
        make_gaussians([[0.1, -0.05, 2.5]], [[math.log(0.35), math.log(0.12), math.log(0.2)]],
                       [[0.8, 0.3, -0.4, 0.5]], [0.7 + t], rgb=[0.9, 0.4, 0.2]),
        cam, RenderConfig(background=(0.3, 0.6, 0.2))), TWEAKS)
    g = scene.gaussians
    v = rng.normal(size=(H, W, 3))
    prof = out.cache["profile"]
    g2d, lists = out.cache["g2d"], out.cache["lists"]
    bg = np.asarray(scene.config.background)
    vc = refgs.composite_backward(g2d, lists, W, H, prof, bg, out.final_T, v, None, None)
    assert all_finite(out.image, out.alpha, *vc.values(), *render_backward(out, v).to_dict().values())
    A, B, C = out.conics[0]
    assert abs(B) > 0.05 * max(A, C)                    # a genuinely rotated conic

    # (1) B moves both symmetric entries: FD in B equals refgs' v_conics[1]
    def loss_B(b):
        return float(np.sum(v * refgs.composite(dict(g2d, conics=np.array([[A, b[0], C]])),
                                                lists, W, H, prof, bg)["image"]))
    fd_B = fd_gradient(loss_B, np.array([B]))[0]
    assert vc["v_conics"][0, 1] == pytest.approx(fd_B, rel=1e-6)

    # (2) one symmetric entry alone, evaluated independently: alpha = o exp(-0.5 d^T Q d) with
    # Q = [[A, Q01], [Q10, C]] -- the derivative in Q01 is the original's -0.5 G dx dy dL/dG
    m, o, col = out.means2d[0], out.opacities[0], out.colors[0]
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dx, dy = m[0] - jj, m[1] - ii

    def loss_Q01(q01):
        a = o * np.exp(-0.5 * (A * dx * dx + (q01[0] + B) * dx * dy + C * dy * dy))
        a = np.where(a >= ALPHA_MIN, a, 0)
        return float(np.sum(v * (a[..., None] * col + (1 - a[..., None]) * bg)))
    assert loss_Q01(np.array([B])) == pytest.approx(float(np.sum(v * out.image)), rel=1e-12)
    fd_Q01 = fd_gradient(loss_Q01, np.array([B]))[0]
    G = np.exp(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)
    dL_dG = np.where(out.n_contrib == 1, o * np.einsum("hwc,c->hw", v, col - bg), 0)
    original_slot = float(np.sum(-0.5 * G * dx * dy * dL_dG))
    assert original_slot == pytest.approx(fd_Q01, rel=1e-6)
    assert original_slot == pytest.approx(0.5 * vc["v_conics"][0, 1], rel=1e-9)
    # transcription of the original: -0.5 slots, then computeCov2D's dL/d(a, b, c) with its x2;
    # equal to refgs' chain (PRJ-07 step 1); the "fixed" -1 slot with the x2 kept is not
    gx = float(np.sum(-0.5 * G * dx * dx * dL_dG))
    gw = float(np.sum(-0.5 * G * dy * dy * dL_dG))
    a, b, c = out.cov2d[0]
    ours = conic_to_cov2d_grad(out.cov2d, vc["v_conics"])
    orig = inria_dL_dcov2d(a, b, c, gx, original_slot, gw)
    fixed = inria_dL_dcov2d(a, b, c, gx, 2 * original_slot, gw)
    for k in range(3):
        assert orig[k] == pytest.approx(float(ours[k][0]), rel=1e-9)
    assert abs(fixed[1] - ours[1][0]) > 0.5 * abs(ours[1][0])

    # (3) the full chain: dL/dSigma3D of refgs, symmetric pairs, against FD through the
    # projection and compositing (the original's 6-vector convention: off-diagonals summed)
    proj = out.cache["proj"]
    _, v_cov3d = refgs.project_gaussians_backward(proj, cam, vc["v_means2d"], vc["v_conics"],
                                                  vc["v_depths"])
    cov = out.cache["cov"]["cov3d"]

    def loss_cov(flat):
        c3 = flat.reshape(1, 3, 3)
        c3 = 0.5 * (c3 + np.swapaxes(c3, 1, 2))
        p = refgs.project_gaussians(g.means, c3, out.cache["o_sig"], cam, prof)
        g2 = dict(g2d, conics=p["conics"], means2d=p["means2d"])
        return float(np.sum(v * refgs.composite(g2, lists, W, H, prof, bg)["image"]))
    sym = v_cov3d[0] + v_cov3d[0].T - np.diag(np.diag(v_cov3d[0]))   # pair gradient, diag once
    fd = np.zeros((3, 3))
    for i in range(3):
        for j in range(i, 3):
            def f(s, i=i, j=j):
                c3 = cov[0].copy()
                c3[i, j] += s[0]
                if i != j:
                    c3[j, i] += s[0]
                return loss_cov(c3.ravel())
            fd[i, j] = fd_gradient(f, np.zeros(1), h=1e-7)[0]
    iu = np.triu_indices(3)
    assert_grad_close(sym[iu], fd[iu], "d/dSigma3D (symmetric pairs)")


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("shape", ["isotropic", "anisotropic"])
def test_hard04_single_gaussian_units(profile, shape):
    """HARD-04 (gsplat #91): one Gaussian.  Gradients.means2d is dL/d(u, v) in pixels (FD in
    pixels); the original's mean2D gradient is in NDC, dL/dndc = dL/dpix * (0.5 W, 0.5 H)
    (ndc2Pix(v, S) = ((v + 1) S - 1) / 2); the 3D mean gradient is unit-free and FD-consistent."""
    cam = identity_camera()
    ls = [[math.log(0.2)] * 3] if shape == "isotropic" else \
        [[math.log(0.25), math.log(0.15), math.log(0.2)]]
    scene, out = smooth_scene(lambda t: Scene(
        make_gaussians([[0.15, -0.1, 3.0]], ls, [[0.9, -0.2, 0.3, 0.1]], [0.4 + t],
                       rgb=[0.8, 0.3, 0.6], k=4),
        cam, RenderConfig(profile=profile)), TWEAKS)
    g = scene.gaussians
    rng = np.random.default_rng(4)
    v = rng.normal(size=(H, W, 3))
    grads = render_backward(out, v)
    g2d, lists, prof = out.cache["g2d"], out.cache["lists"], out.cache["profile"]

    def loss_pix(m2):
        return float(np.sum(v * refgs.composite(dict(g2d, means2d=m2.reshape(1, 2)), lists, W, H,
                                                prof, np.zeros(3))["image"]))
    fd_pix = fd_gradient(loss_pix, out.means2d[0].copy())
    assert_grad_close(grads.means2d[0], fd_pix, "d/dmeans2d (pixels)")

    def loss_ndc(ndc):
        pix = ((ndc + 1) * np.array([W, H]) - 1) / 2 + 0.5     # original pixel coords + 0.5
        return loss_pix(pix)
    ndc0 = (2 * (out.means2d[0] - 0.5) + 1) / np.array([W, H]) - 1
    fd_ndc = fd_gradient(loss_ndc, ndc0)
    assert_grad_close(grads.means2d[0] * np.array([0.5 * W, 0.5 * H]), fd_ndc, "NDC conversion")
    render_fd_check(scene, {"v_image": v}, rng=rng, sh_samples=12)     # every raw parameter


def _synthetic_real_like_camera(width=48):
    """Fallback when the fern data or pycolmap is absent: an off-centre camera with fx != fy
    and a random cloud of 'SfM points' in front of it."""
    rng = np.random.default_rng(55)
    cam = make_camera(rng, width, 36, principal_jitter=5.0)
    t = np.stack([rng.uniform(-1, 1, 400), rng.uniform(-0.7, 0.7, 400), rng.uniform(2, 6, 400)], -1)
    return cam, (t - cam.translation) @ cam.rotation


def _fern_camera(width=48):
    """A real COLMAP camera (fern, first image, intrinsics scaled to ``width``) and the
    reconstruction's points; the synthetic fallback when the data or pycolmap is missing."""
    try:
        import pycolmap
    except ImportError:
        return _synthetic_real_like_camera(width)
    sparse = data_root() / "fern" / "sparse" / "0"
    if not (sparse / "cameras.bin").exists():
        return _synthetic_real_like_camera(width)
    rec = pycolmap.Reconstruction(str(sparse))
    image = rec.images[min(rec.images)]
    cam = rec.cameras[image.camera_id]
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    E = np.eye(4)
    E[:3, :] = cfw.matrix()
    s = width / cam.width
    # SIMPLE_RADIAL / SIMPLE_PINHOLE: (f, cx, cy, ...); PINHOLE-like: (fx, fy, cx, cy)
    p = np.asarray(cam.params, float)
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name.startswith("SIMPLE") \
        else (p[0], p[1], p[2], p[3])
    K = np.array([[fx * s, 0, cx * s], [0, fy * s, cy * s], [0, 0, 1.0]])
    height = int(round(cam.height * s))
    points = np.array([pt.xyz for pt in rec.points3D.values()])
    return Camera(E, K, width, height), points


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard05_real_camera_geometry(profile):
    """HARD-05 (gsplat #157, PR #172): a real COLMAP pose and intrinsics (fern via pycolmap,
    scaled to 48 px wide, radial distortion dropped: refgs is a pinhole model; a synthetic
    off-centre camera when the data is absent) with Gaussians at reconstructed points in its
    frustum: FD-consistent gradients; the profiles' frustum limits follow PRF-02."""
    cam, points = _fern_camera()
    li = frustum_limits(cam, refgs.INRIA, np.dtype(np.float64))
    lg = frustum_limits(cam, refgs.GSPLAT, np.dtype(np.float64))
    tx, ty = cam.width / (2 * cam.fx), cam.height / (2 * cam.fy)
    assert np.allclose(li, [1.3 * tx, 1.3 * tx, 1.3 * ty, 1.3 * ty], rtol=1e-14)
    assert np.allclose(lg, [cam.cx / cam.fx + 0.3 * tx, (cam.width - cam.cx) / cam.fx + 0.3 * tx,
                            cam.cy / cam.fy + 0.3 * ty, (cam.height - cam.cy) / cam.fy + 0.3 * ty],
                       rtol=1e-14)
    centred = np.isclose([cam.cx, cam.cy], [cam.width / 2, cam.height / 2], rtol=1e-12)
    assert np.allclose(li[:2], lg[:2], rtol=1e-12) == centred[0]
    assert np.allclose(li[2:], lg[2:], rtol=1e-12) == centred[1]
    t = refgs.world_to_camera(points, cam.world_to_camera)
    uv = t[:, :2] / t[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (t[:, 2] > 0.5) & (uv[:, 0] > 2) & (uv[:, 0] < cam.width - 2) \
        & (uv[:, 1] > 2) & (uv[:, 1] < cam.height - 2)
    cand = np.flatnonzero(inside)
    assert cand.size > 10
    for seed in range(30):
        rng = np.random.default_rng(seed)
        idx = rng.choice(cand, 3, replace=False)
        z = t[idx, 2]
        sig = rng.uniform(1.5, 3.0, 3) * z / cam.fx
        ls = np.log(sig)[:, None] + rng.uniform(-0.4, 0.4, (3, 3))
        sh = 0.1 * rng.normal(size=(3, 4, 3))
        sh[:, 0] = (rng.uniform(0.2, 0.9, (3, 3)) - 0.5) / SH_C0
        g = Gaussians(points[idx], ls, rng.normal(size=(3, 4)), rng.uniform(-1, 2, 3), sh)
        scene = Scene(g, cam, RenderConfig(profile=profile, background=(0.5, 0.5, 0.5)), seed)
        out = scene.render()
        if out.visible.all() and far_from_thresholds(out):
            break
    else:
        pytest.fail("no scene away from the thresholds")
    cot = random_cotangents(rng, cam.height, cam.width)
    render_fd_check(scene, cot, rng=rng)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard06_tiny_scales_and_quats(profile):
    """HARD-06 (gsplat #248): scales 1e-4 .. 1e-7, a near-singular 2D covariance before the
    dilation (antialiased compensation near 0), quaternion norms 1e-30 and 1e-200: finite forward
    and backward, rotation-invariant to the quaternion's scale; a zero quaternion is a ValueError."""
    cam = identity_camera()
    rng = np.random.default_rng(6)
    n = 5
    means = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), rng.uniform(2, 3, n)], -1)
    ls = np.log(rng.uniform(1e-7, 1e-4, (n, 3)))
    ls[0] = [math.log(0.3), math.log(0.2), math.log(1e-7)]      # flat disc (rank-2 Sigma)
    ls[1] = [math.log(0.4), math.log(1e-7), math.log(1e-7)]     # needle: rank-1 Sigma and Sigma_2D
    q = rng.normal(size=(n, 4))
    g = make_gaussians(means, ls, q, rng.uniform(0.5, 3, n))
    cfgs = [RenderConfig(profile=profile, background=(0.2, 0.2, 0.2))]
    if profile == "gsplat":
        cfgs.append(RenderConfig(profile=profile, antialiased=True))
    v = rng.normal(size=(H, W, 3))
    for cfg in cfgs:
        for dtype in (np.float64, np.float32):
            out = render(g.astype(dtype), cam, cfg)
            gr = render_backward(out, v, rng.normal(size=(H, W)), rng.normal(size=(H, W)))
            assert all_finite(out.image, out.conics, out.cov2d, *gr.to_dict().values())
            if not cfg.antialiased:                 # (antialiased: tiny ones have comp ~ 0)
                assert out.visible.all()
            assert np.all(out.cov2d[2:, [0, 2]] >= 0.3 - 1e-6)     # the dilation dominates
        if cfg.antialiased:
            comp = out.cache["proj"]["comp"]
            assert comp[1] < 0.01 and comp[2:].max() < 0.01        # needle / tiny: comp ~ 0
    # quaternion norms: the same rotation, gradients scaled by 1 / |q|
    ref = render(g, cam, cfgs[0])
    gref = render_backward(ref, v)
    for lam in (1e-30, 1e-200):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            out = render(g.replace(quats=q * lam), cam, cfgs[0])
            gr = render_backward(out, v)
        assert np.allclose(out.image, ref.image, rtol=0, atol=1e-14)
        assert all_finite(gr.quats)
        assert np.allclose(gr.quats * lam, gref.quats, rtol=1e-10, atol=1e-12 * np.abs(gref.quats).max())
    # FD through the tiny Gaussians (means and opacities; scale gradients are ~ s^2 ~ 1e-14)
    scene = Scene(g, cam, cfgs[0])
    assert far_from_thresholds(ref), threshold_distances(ref)
    render_fd_check(scene, {"v_image": v}, rng=rng, fields=("means", "opacity_logits"))
    bad = g.replace(quats=np.concatenate([q[:4], np.zeros((1, 4))]))
    with pytest.raises(ValueError, match=r"Gaussians\.quats"):
        render(bad, cam, cfgs[0])


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_hard07_opaque_stack(profile, dtype):
    """HARD-07 (gsplat #556 / PR #541), RAS-05, RAS-10: stacks of 2 .. 20 Gaussians with opacity
    -> 1 (logit up to 20) on one pixel: final_T >= 1e-4 (strictly for gsplat), the stopping
    Gaussian absent from the image, finite gradients; at saturated fragments gsplat's opacity
    gradient is exactly 0 and inria's is not."""
    cam = identity_camera(cx=W / 2 + 0.5, cy=H / 2 + 0.5)      # the axis hits pixel (12, 16)
    ci, cj = H // 2, W // 2
    rng = np.random.default_rng(7)
    Tmin = dtype(T_MIN)
    for n in (2, 5, 20):
        for logit in (5.0, 20.0):
            z = 2.0 + 0.05 * np.arange(n)
            means = np.stack([np.zeros(n), np.zeros(n), z], -1)
            rgb = rng.uniform(0.1, 0.9, (n, 3))
            g = make_gaussians(means, [[math.log(0.1)] * 3], [[1.0, 0, 0, 0]], logit,
                               rgb=rgb).astype(dtype)
            cfg = RenderConfig(profile=profile, background=(1.0, 1.0, 1.0))
            out = render(g, cam, cfg)
            if profile == "gsplat":
                assert np.all(out.final_T > Tmin)
            else:
                assert np.all(out.final_T >= Tmin)
            k = int(out.n_contrib[ci, cj])
            assert 1 <= k <= n and out.final_T[ci, cj] < 1e-2            # saturated
            assert k < n or n == 2                                       # stopped early
            if k < n:
                # the stopping Gaussian (list position k + 1, i.e. index k) is absent
                recoloured = g.replace(sh=g.sh.copy())
                recoloured.sh[k, 0] += dtype(3.0)
                assert np.array_equal(render(recoloured, cam, cfg).image[ci, cj],
                                      out.image[ci, cj])
            v = np.zeros((H, W, 3))
            v[ci, cj] = [1.0, -0.5, 0.25]
            gr = render_backward(out, rng.normal(size=(H, W, 3)), rng.normal(size=(H, W)),
                                 rng.normal(size=(H, W)))
            assert all_finite(*gr.to_dict().values())
            c = out.cache
            vc = refgs.composite_backward(c["g2d"], c["lists"], W, H, c["profile"],
                                          np.ones(3, dtype), out.final_T, v.astype(dtype), None, None)
            saturated = out.opacities[:k] > c["profile"].alpha_max         # o G > cap at G = 1
            if saturated.any():
                v_o = vc["v_opacities"][:k][saturated]
                if profile == "gsplat":
                    assert np.all(v_o == 0)
                else:
                    assert np.any(v_o != 0)
            assert np.all(vc["v_opacities"][k:] == 0) and np.all(vc["v_colors"][k:] == 0)


def test_hard08_last_contributor():
    """HARD-08 (gaussian-splatting #1130), RAS-06: n_contrib equals the per-pixel loop's and
    agrees with the backward: with dL/dimage one-hot at a pixel, exactly the Gaussians blended
    there (positions up to n_contrib, early termination and skips included) receive a colour
    gradient; a Gaussian behind the stop gets exactly zero gradient and moving it changes
    neither the image nor the other gradients."""
    rng = np.random.default_rng(8)
    cam = make_camera(rng, W, H)
    g = place_gaussians(rng, cam, 10, sigma_px=(3.0, 7.0), logits=(3.0, 6.0), offscreen=-0.3)
    for profile in ("inria", "gsplat"):
        out = render(g, cam, RenderConfig(profile=profile))
        assert all_finite(out.image, *render_backward(out, np.ones((H, W, 3))).to_dict().values())
        ref = composite_loop_of(out)
        assert np.array_equal(out.n_contrib, ref["n_contrib"])
        lists = out.cache["lists"]
        gx = -(-W // TILE_SIZE)
        early = 0
        pixels = [(i, j) for i in range(0, H, 3) for j in range(0, W, 3)]
        for i, j in pixels:
            v = np.zeros((H, W, 3))
            v[i, j] = 1.0
            vc = refgs.composite_backward(out.cache["g2d"], lists, W, H, out.cache["profile"],
                                          np.zeros(3), out.final_T, v, None, None)
            got = set(np.flatnonzero(np.any(vc["v_colors"] != 0, axis=1)))
            assert got == set(ref["blended"][(i, j)]), (i, j)
            t = (i // TILE_SIZE) * gx + j // TILE_SIZE
            tile_list = lists["gauss"][lists["offsets"][t]:lists["offsets"][t + 1]].tolist()
            k = out.n_contrib[i, j]
            if k:
                assert tile_list[k - 1] == ref["blended"][(i, j)][-1]
                assert all(tile_list.index(x) < k for x in got)
            early += out.final_T[i, j] < 1e-3 and k < len(tile_list)
        assert early > 0, "the scene must contain early-terminated pixels"

    # a small Gaussian entirely behind the stop of an opaque stack: zero gradient, and moving it
    # (still behind the stop) changes neither the image nor any other gradient
    cam = identity_camera()
    n = 5
    stack = make_gaussians(np.stack([np.zeros(n), np.zeros(n), 2.0 + 0.1 * np.arange(n)], -1),
                           [[math.log(0.6)] * 3], [[1.0, 0, 0, 0]], 7.0,
                           rgb=rng.uniform(0.1, 0.9, (n, 3)))
    v = rng.normal(size=(H, W, 3))
    for profile in ("inria", "gsplat"):
        outs = []
        for shift in (0.0, 0.02):
            hidden = make_gaussians([[shift, 0.01, 3.0]], [[math.log(0.03)] * 3], [[1.0, 0, 0, 0]], 2.0)
            g = Gaussians(*(np.concatenate([getattr(stack, f), getattr(hidden, f)])
                            for f in Gaussians.FIELDS))
            out = render(g, cam, RenderConfig(profile=profile))
            assert out.visible[n]
            gr = render_backward(out, v)
            assert all(np.all(arr[n] == 0) for arr in gr.to_dict().values())
            outs.append((out, gr))
        (o1, g1), (o2, g2) = outs
        assert np.allclose(o1.image, o2.image, rtol=0, atol=1e-15)
        assert np.array_equal(o1.n_contrib, o2.n_contrib)
        for name in Gradients.PARAM_FIELDS:
            a1, a2 = getattr(g1, name)[:n], getattr(g2, name)[:n]
            assert np.allclose(a1, a2, rtol=1e-13, atol=1e-15 * np.abs(a1).max()), name


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard09_support_collapse_after_reset(profile):
    """HARD-09 (gsplat #1011), RAS-04: after an opacity reset to 0.01 a Gaussian keeps gradients
    exactly where some fragment has alpha >= 1/255 (within ~1.37 sigma of its centre): every
    on-image mean, any size (the dilation guarantees G >= 0.435 at the nearest pixel centre); the
    gradient is exactly zero when every fragment is below 1/255 (mean off the image, or
    o = 0.008 on a pixel corner with the smallest footprint)."""
    cam = identity_camera()
    reset = math.log(0.01 / 0.99)
    big = [[math.log(0.6)] * 3]
    v = np.random.default_rng(9).normal(size=(H, W, 3))
    # centred: fragments near the centre have alpha = 0.01 G >= 1/255 -> gradient exists
    scene, out = smooth_scene(lambda t: Scene(make_gaussians([[0.02 + 0.1 * t, 0.03, 3.0]], big,
                                                             [[1.0, 0, 0, 0]], reset),
                                              cam, RenderConfig(profile=profile)), TWEAKS)
    g = scene.gaussians
    assert 0.009 < out.alpha.max() <= 0.01 and out.n_contrib.max() == 1
    sigma = math.sqrt(out.cov2d[0, 0])
    assert np.count_nonzero(out.alpha) < np.pi * (1.4 * sigma) ** 2     # only the core blends
    gr = render_backward(out, v)
    assert all_finite(out.image, *gr.to_dict().values())
    assert gr.opacity_logits[0] != 0 and np.any(gr.means != 0)
    render_fd_check(scene, {"v_image": v}, rng=np.random.default_rng(0),
                    fields=("opacity_logits", "means"))
    # centre 2.5 sigma off-screen: the image holds only the tail (alpha < 1/255 everywhere)
    off = (W / 2 + 2.5 * sigma) * 3.0 / F
    g_off = g.replace(means=np.array([[off, 0.0, 3.0]]))
    out_off = render(g_off, cam, RenderConfig(profile=profile))
    # inria evaluates it (its 3-sigma tiles reach the image), gsplat's opacity-aware box
    # (extend sqrt(2 ln 2.55) = 1.37) already culls it: no fragment either way
    assert out_off.visible[0] == (profile == "inria") and np.all(out_off.alpha == 0)
    gr_off = render_backward(out_off, v)
    for name, arr in gr_off.to_dict().items():
        assert np.all(arr == 0), name
    # several sizes and positions (one mean on a pixel corner, one the smallest footprint,
    # sigma^2 = 0.3): the standard reset value 0.01 keeps a live fragment and a gradient
    for mean, scale in [((0.0, 0.0), 1e-6), ((0.0, 0.0), 0.2), ((0.3, -0.2), 0.05),
                        ((0.5, 0.4), 1e-3)]:
        gs = make_gaussians([[mean[0], mean[1], 3.0]], [[math.log(scale)] * 3], [[1.0, 0, 0, 0]], reset)
        o_s = render(gs, cam, RenderConfig(profile=profile))
        assert render_backward(o_s, v).opacity_logits[0] != 0, (mean, scale)
    # mean on a pixel corner ((u, v) = (cx, cy) = (16, 12)), smallest footprint, o = 0.008:
    # the nearest centres see 0.008 exp(-0.5 * 0.5 / 0.3) = 0.0035 < 1/255 -> exactly zero
    gs = make_gaussians([[0.0, 0.0, 3.0]], [[math.log(1e-6)] * 3], [[1.0, 0, 0, 0]],
                        math.log(0.008 / 0.992))
    o_s = render(gs, cam, RenderConfig(profile=profile))
    assert o_s.means2d[0].tolist() == [16.0, 12.0] and o_s.visible[0]
    assert np.all(o_s.alpha == 0)
    assert all(np.all(a == 0) for a in render_backward(o_s, v).to_dict().values())
    # just below 1/255 everywhere (centred): exactly zero, both profiles (gsplat also culls)
    g_low = g.replace(opacity_logits=np.array([math.log(0.0039 / 0.9961)]))
    out_low = render(g_low, cam, RenderConfig(profile=profile))
    assert np.all(out_low.alpha == 0) and out_low.visible[0] == (profile == "inria")
    assert all(np.all(a == 0) for a in render_backward(out_low, v).to_dict().values())


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("background,with_alpha", [("white", False), ("random", False),
                                                    ("random", True)])
def test_hard10_background_gradient(profile, background, with_alpha):
    """HARD-10 (diff-gaussian-rasterization #86), RAS-07: with a white or random background, with
    and without v_alpha, every parameter's gradient matches FD (the background term
    -T_final / (1 - a) bg . dL/dC enters once); a backward that counts it twice does not;
    dL/dbg = sum T_final dL/dC."""
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        cam = make_camera(rng, W, H)
        g = place_gaussians(rng, cam, 3, sigma_px=(2.0, 4.0), logits=(0.5, 2.5), offscreen=0.0)
        bg = (1.0, 1.0, 1.0) if background == "white" else tuple(rng.uniform(0.3, 1.0, 3))
        scene = Scene(g, cam, RenderConfig(profile=profile, background=bg), seed)
        out = scene.render()
        if out.visible.all() and far_from_thresholds(out):
            break
    else:
        pytest.fail("no scene away from the thresholds")
    cot = random_cotangents(rng, H, W, alpha=with_alpha, depth=False)
    render_fd_check(scene, cot, rng=rng)
    # the double-counted variant (the 3dgs_accel bug): the backward's background term with 2 bg
    prof = out.cache["profile"]
    args = (out.cache["g2d"], out.cache["lists"], W, H, prof)
    once = refgs.composite_backward(*args, np.asarray(bg), out.final_T, cot["v_image"],
                                    cot["v_alpha"], None)
    twice = refgs.composite_backward(*args, 2 * np.asarray(bg), out.final_T, cot["v_image"],
                                     cot["v_alpha"], None)

    def loss_o(o):
        c = refgs.composite(dict(out.cache["g2d"], opacities=o), out.cache["lists"], W, H, prof,
                            np.asarray(bg))
        return float(np.sum(cot["v_image"] * c["image"])
                     + (np.sum(cot["v_alpha"] * c["alpha"]) if with_alpha else 0.0))
    fd_o = fd_gradient(loss_o, out.opacities.copy())
    assert_grad_close(once["v_opacities"], fd_o, "d/dopacity")
    assert np.max(np.abs(twice["v_opacities"] - fd_o)) > 1e-2 * np.max(np.abs(fd_o))
    # the background's own gradient (not a parameter of Gradients): L is linear in bg
    fd_bg = fd_gradient(lambda b: scalar_loss(scene.render(background=tuple(b)), cot), np.asarray(bg))
    assert np.allclose(fd_bg, np.einsum("hw,hwc->c", out.final_T, cot["v_image"]), rtol=1e-8)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_hard11_huge_splats_no_overflow(profile, dtype):
    """HARD-11 (gaussian-splatting #28, gsplat #464): huge scales near the near plane cover every
    tile: the intersection count is held in int64, radii saturate instead of wrapping, output and
    gradients are finite."""
    width = height = 128
    cam = identity_camera(fx=100.0, cx=64.0, cy=64.0, width=width, height=height)
    n = 12
    rng = np.random.default_rng(11)
    near = refgs.get_profile(profile).near
    z = near * rng.uniform(1.05, 1.5, n)
    means = np.stack([rng.uniform(-0.5, 0.5, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
    ls = np.log(rng.uniform(1e2, 1e4, (n, 3)))
    ls[0] = 20.0                                          # radius ~ 1e11 px: saturates int32
    ls[1] = 25.0 if dtype == np.float64 else 21.0        # the spec's largest test value (f64)
    g = make_gaussians(means, ls, rng.normal(size=(n, 4)), rng.uniform(-3, -1, n)).astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = render(g, cam, RenderConfig(profile=profile))
        gr = render_backward(out, np.ones((height, width, 3)))
    n_tiles = (width // TILE_SIZE) * (height // TILE_SIZE)
    lists = out.cache["lists"]
    assert lists["gauss"].dtype == np.int64 and lists["offsets"].dtype == np.int64
    assert out.visible.all()
    assert int(lists["offsets"][-1]) == n * n_tiles
    assert out.radii.dtype == np.int32 and np.all(out.radii > 0)
    assert out.radii[0].tolist() == out.radii[1].tolist() == [np.iinfo(np.int32).max] * 2
    assert all_finite(out.image, out.alpha, *gr.to_dict().values())
    # the tile rectangle of an unbounded radius is clipped to the grid without overflow
    rect, ok = tile_rectangles(np.array([[10.0, 10.0], [1e30, -1e30]]), np.array([np.inf, 1e300]),
                               np.array([np.inf, 1e300]), width, height, refgs.get_profile(profile))
    assert rect.dtype == np.int64 and ok[0]
    assert rect[0].tolist() == [0, width // TILE_SIZE, 0, height // TILE_SIZE]


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_hard12_empty_and_all_culled(profile, dtype):
    """HARD-12 (gaussian-splatting #472), API-06: N = 0 with K in {1, 4, 16} gives zero-size
    gradients with the right trailing shapes (sh keeps its K); all-culled scenes (behind the
    camera, before the near plane, off-screen, below 1/255 for gsplat) give all-zero gradients
    of full shape, without error."""
    cam = identity_camera()
    cfg = RenderConfig(profile=profile, background=(0.5, 0.5, 0.5))
    v = np.ones((H, W, 3))
    for k in (1, 4, 16):
        out = render(Gaussians.empty(k=k, dtype=dtype), cam, cfg)
        gr = render_backward(out, v, np.ones((H, W)), np.ones((H, W)))
        assert gr.means.shape == (0, 3) and gr.log_scales.shape == (0, 3)
        assert gr.quats.shape == (0, 4) and gr.opacity_logits.shape == (0,)
        assert gr.sh.shape == (0, k, 3) and gr.means2d.shape == (0, 2)
        assert all(a.dtype == dtype for a in gr.to_dict().values())
    means = [[0, 0, -1.0], [0, 0, 0.005], [50.0, 0, 1.0], [0, -80.0, 2.0]]
    logits = [1.0, 1.0, 1.0, 1.0]
    if profile == "gsplat":
        means.append([0.0, 0.0, 2.0])
        logits.append(math.log(0.003 / 0.997))              # o < 1/255: culled by gsplat
    g = make_gaussians(means, [[math.log(0.05)] * 3], [[1.0, 0, 0, 0]], logits, k=4).astype(dtype)
    out = render(g, cam, cfg)
    assert not out.visible.any() and np.all(out.image == dtype(0.5))
    gr = render_backward(out, v, np.ones((H, W)), np.ones((H, W)))
    for name, arr in gr.to_dict().items():
        assert arr.shape[0] == len(means) and np.all(arr == 0), name


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard13_rank1_edge_on(profile):
    """HARD-13 (UnityGaussianSplatting PR #14): a flat disc seen exactly and nearly edge-on
    (rank-1 2D covariance before the dilation) and a needle seen end-on (rank 0): finite conics,
    radius bounded by the projected extent plus the dilation, FD-consistent where smooth."""
    cam = identity_camera()
    z = 2.5
    # disc in the x-z plane (normal along y, one scale 1e-8 .. 1e-9 of the others): seen from the
    # camera on +z it is a horizontal line; rotated about x through the exactly edge-on angle
    for tilt in (-1e-4, -1e-9, 0.0, 1e-9, 1e-4):
        q = [math.cos(tilt / 2), math.sin(tilt / 2), 0, 0]
        g = make_gaussians([[0.0, 0.0, z]], [[math.log(0.3), math.log(1e-9), math.log(0.3)]], q, 1.5)
        out = render(g, cam, RenderConfig(profile=profile))
        proj = out.cache["proj"]
        cov2d_raw = proj["J"][0] @ proj["cov_cam"][0] @ proj["J"][0].T
        lam = np.linalg.eigvalsh(cov2d_raw)
        assert lam[0] < 1e-6 * lam[1]                           # rank-1 before the dilation
        assert all_finite(out.image, out.conics)
        assert np.all(np.abs(out.conics) <= 1 / 0.3 + 1e-9)       # inverse of >= 0.3 I
        assert proj["det"][0] > 0 and out.visible[0]
        bound = 3.33 * math.sqrt(lam[1] + 0.3 + math.sqrt(0.1))
        assert out.radii[0].max() <= math.ceil(bound)
        assert out.radii[0].max() >= math.floor(3 * math.sqrt(lam[1]))
        gr = render_backward(out, np.ones((H, W, 3)))
        assert all_finite(*gr.to_dict().values())
    # a needle along the optical axis, seen end-on: a dot of the dilation's size
    g = make_gaussians([[0.0, 0.0, z]], [[math.log(1e-9), math.log(1e-9), math.log(0.5)]],
                       [[1.0, 0, 0, 0]], 1.5)
    out = render(g, cam, RenderConfig(profile=profile))
    assert out.cov2d[0] == pytest.approx([0.3, 0.0, 0.3], abs=1e-3)
    assert out.radii[0].max() <= math.ceil(3.33 * math.sqrt(0.3 + math.sqrt(0.1)))
    # FD on the nearly edge-on disc
    scene, out = smooth_scene(lambda t: Scene(
        make_gaussians([[0.05, 0.02, z]], [[math.log(0.3), math.log(1e-6), math.log(0.3)]],
                       [[math.cos(0.05), math.sin(0.05), 0, 0]], 1.0 + t),
        cam, RenderConfig(profile=profile, background=(0.1, 0.1, 0.1))), TWEAKS)
    render_fd_check(scene, {"v_image": np.random.default_rng(13).normal(size=(H, W, 3))},
                    rng=np.random.default_rng(0), fields=("means", "quats", "opacity_logits"))
