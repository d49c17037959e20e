"""Conventions CNV-01 .. CNV-11 (docs/spec/conventions.md): one test per clause, each checking
its rule on a concrete, hand-built case (the docs cite these test names)."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.special as sp
from scipy.spatial.transform import Rotation

import refgs
from refgs import Camera, Gaussians, RenderConfig, render, render_backward
from refgs.constants import SH_C0
from refgs.projection import frustum_limits

from strategies import make_camera, place_gaussians

W, H = 32, 24
#: Power-of-two focal and depth: fx * x / z is then exact for the dyadic x used below.
F, Z = 32.0, 2.0


def identity_camera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H) -> Camera:
    """Camera at the origin looking down world +z (world frame = camera frame)."""
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return Camera(np.eye(4), K, width, height)


def one_gaussian(mean, log_scales=(math.log(0.1),) * 3, quat=(1.0, 0, 0, 0), logit=0.0,
                 rgb=(0.8, 0.6, 0.4), k=1, dtype=np.float64) -> Gaussians:
    sh = np.zeros((1, k, 3))
    sh[0, 0] = (np.asarray(rgb) - 0.5) / SH_C0
    return Gaussians(np.array([mean], dtype), np.array([log_scales], dtype),
                     np.array([quat], dtype), np.array([logit], dtype), sh.astype(dtype))


def test_cnv01_camera_frame():
    """CNV-01: OpenCV frame -- +x lands right of cx, +y lands below cy, z > 0 is in front."""
    cam = identity_camera()
    for mean, sign_u, sign_v in [((0.5, 0, 3), 1, 0), ((-0.5, 0, 3), -1, 0),
                                 ((0, 0.4, 3), 0, 1), ((0, -0.4, 3), 0, -1)]:
        out = render(one_gaussian(mean), cam)
        u, v = out.means2d[0]
        assert np.sign(round(u - cam.cx, 9)) == sign_u
        assert np.sign(round(v - cam.cy, 9)) == sign_v
        # the rendered blob sits on the same side: its brightest pixel's column / row
        i, j = np.unravel_index(np.argmax(out.alpha), out.alpha.shape)
        if sign_u:
            assert np.sign(j + 0.5 - cam.cx) == sign_u
        if sign_v:
            assert np.sign(i + 0.5 - cam.cy) == sign_v
    # a point behind the camera would project on screen (fx x / z + cx) but is not rendered
    out = render(one_gaussian((0.0, 0.0, -3.0)), cam)
    assert not out.visible[0] and out.radii[0].tolist() == [0, 0]
    assert np.all(out.alpha == 0)


def test_cnv02_world_to_camera():
    """CNV-02: t = R mu + t_w with E = [[R, t_w], [0, 1]]; centre -R^T t_w; E is not transposed."""
    rng = np.random.default_rng(2)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    tw = rng.normal(size=3)
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, tw
    cam = Camera(E, identity_camera().K, W, H)
    assert np.allclose(cam.center, -R.T @ tw, atol=1e-15)
    # a Gaussian on the optical axis, 3 units in front of the centre, projects to (cx, cy)
    mean = cam.center + R.T @ np.array([0.0, 0.0, 3.0])
    out = render(one_gaussian(mean), cam)
    assert np.allclose(out.cache["proj"]["t"][0], R @ mean + tw, atol=1e-14)
    assert np.allclose(out.means2d[0], [cam.cx, cam.cy], atol=1e-12)
    assert out.depths[0] == pytest.approx(3.0, abs=1e-14)
    # moving the camera by delta (in camera coordinates) == moving the scene by -R^T delta
    g = one_gaussian(mean + R.T @ np.array([0.3, -0.2, 0.1]))
    delta = np.array([0.05, 0.02, -0.1])
    E2 = E.copy()
    E2[:3, 3] += delta
    a = render(g, Camera(E2, cam.K, W, H)).image
    b = render(g.replace(means=g.means + R.T @ delta), cam).image
    assert np.allclose(a, b, atol=1e-12)
    assert not np.allclose(a, render(g, cam).image, atol=1e-6)     # the move is visible
    # the transposed matrix (the original's world_view_transform layout) is not accepted as is
    Et = E.T.copy()
    with pytest.raises(ValueError, match="Camera.world_to_camera"):
        render(g, Camera(Et, cam.K, W, H))


def test_cnv03_intrinsics():
    """CNV-03: exactly fx = K00, fy = K11, cx = K02, cy = K12 are read; tan(fov/2) = W / (2 fx)."""
    fx, fy, cx, cy = 30.0, 20.0, 13.25, 9.5
    cam = identity_camera(fx, fy, cx, cy)
    mean = (0.3, -0.2, 2.5)
    out = render(one_gaussian(mean), cam)
    assert np.allclose(out.means2d[0], [fx * 0.3 / 2.5 + cx, fy * -0.2 / 2.5 + cy], atol=1e-13)
    # skew and the bottom row are not part of the model
    K2 = cam.K.copy()
    K2[0, 1], K2[2, 2], K2[2, 0] = 7.0, 3.0, 0.5
    out2 = render(one_gaussian(mean), Camera(cam.world_to_camera, K2, W, H))
    assert np.array_equal(out.image, out2.image)
    # the half-angle tangents of the frustum clamp (PRJ-03, PRF-02)
    tan_x, tan_y = W / (2 * fx), H / (2 * fy)
    lims = frustum_limits(cam, refgs.INRIA, np.dtype(np.float64))
    assert np.allclose(lims, [1.3 * tan_x, 1.3 * tan_x, 1.3 * tan_y, 1.3 * tan_y], rtol=1e-15)
    lims = frustum_limits(cam, refgs.GSPLAT, np.dtype(np.float64))
    assert np.allclose(lims, [cx / fx + 0.3 * tan_x, (W - cx) / fx + 0.3 * tan_x,
                              cy / fy + 0.3 * tan_y, (H - cy) / fy + 0.3 * tan_y], rtol=1e-15)
    for bad in (0.0, -5.0):
        K3 = cam.K.copy()
        K3[0, 0] = bad
        with pytest.raises(ValueError, match="Camera.K"):
            render(one_gaussian(mean), Camera(np.eye(4), K3, W, H))


def test_cnv04_quaternion_order():
    """CNV-04: q = (w, x, y, z); (cos t/2, 0, 0, sin t/2) rotates x toward y by t; standard R."""
    t = 0.7
    R = refgs.quat_to_rotmat(np.array([[math.cos(t / 2), 0, 0, math.sin(t / 2)]]))[0]
    assert np.allclose(R @ [1, 0, 0], [math.cos(t), math.sin(t), 0], atol=1e-15)
    assert np.allclose(R @ [0, 0, 1], [0, 0, 1], atol=1e-15)
    # (x, y, z) part about x rotates y toward z
    R = refgs.quat_to_rotmat(np.array([[math.cos(t / 2), math.sin(t / 2), 0, 0]]))[0]
    assert np.allclose(R @ [0, 1, 0], [0, math.cos(t), math.sin(t)], atol=1e-15)
    # against scipy (scalar-last convention) for random unit quaternions; q and -q agree
    rng = np.random.default_rng(4)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    assert np.allclose(refgs.quat_to_rotmat(q), ref, atol=1e-14)
    assert np.allclose(refgs.quat_to_rotmat(-q), ref, atol=1e-14)
    # in an image: a needle along its local x, rotated 90 degrees about the optical axis,
    # turns from horizontal (a > c) to vertical (c > a); at 45 degrees it points down-right (b > 0)
    cam = identity_camera()
    ls = (math.log(0.3), math.log(0.03), math.log(0.03))
    cov = {}
    for deg in (0, 45, 90):
        th = math.radians(deg)
        out = render(one_gaussian((0, 0, 3), ls, (math.cos(th / 2), 0, 0, math.sin(th / 2))), cam)
        cov[deg] = out.cov2d[0]
    assert cov[0][0] > 10 * cov[0][2] and abs(cov[0][1]) < 1e-12
    assert cov[90][2] > 10 * cov[90][0] and abs(cov[90][1]) < 1e-12
    assert cov[45][1] > 0.4 * cov[45][0]


_CNV05_NORMS = [
    ("float64", 1.0), ("float64", 3.7), ("float64", 1e-30), ("float64", 1e-120),
    ("float64", 1e-200), ("float64", 1e-300), ("float64", 1e-310), ("float64", 1e150),
    ("float64", 1e200), ("float64", 1e300),
    ("float32", 1.0), ("float32", 1e-15), ("float32", 1e-30), ("float32", 1e-40),
    ("float32", 1e15), ("float32", 1e30),
]


def test_cnv05_norms_reach_the_near_degenerate_band():
    """CNV-05: both dtypes are tested below QUAT_TINY_NORM (where an eps-guarded normalise fails)."""
    from refgs.constants import QUAT_TINY_NORM
    for dt in ("float32", "float64"):
        assert min(n for d, n in _CNV05_NORMS if d == dt) < QUAT_TINY_NORM * 1e-3


@pytest.mark.parametrize("dtype,norm", _CNV05_NORMS)
def test_cnv05_quaternion_normalisation(dtype, norm):
    """CNV-05: only the direction of q matters (any finite non-zero norm, either dtype, subnormal
    included); the gradient (I - u u^T) v_u / |q| is orthogonal to q, scales like 1/|q| and is
    finite whenever its true value is representable; q = 0 is rejected."""
    dt = np.dtype(dtype)
    rng = np.random.default_rng(5)
    q = rng.normal(size=(6, 4))
    q[0] = [0, 0, 0, 1]                       # exact components survive the scaling
    ls = np.log(rng.uniform(0.1, 1.0, (6, 3)))
    qs = (q * norm).astype(dt)
    assert np.all(np.isfinite(qs)) and np.all(np.any(qs != 0, axis=1))
    # reference from the values actually passed, rescaled by an exact power of two in float64
    k2 = -int(np.floor(np.log2(norm)))
    q64 = np.ldexp(qs.astype(np.float64), k2)
    u_ref = q64 / np.linalg.norm(q64, axis=1, keepdims=True)
    # cotangent scaled so that the true gradient (~ |v| / |q|) is representable in the dtype
    v_scale = min(1.0, norm * 1e6)
    v_cov = rng.normal(size=(6, 3, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        u, qn, _ = refgs.normalize_quats(qs)
        fwd = refgs.covariance_3d(qs, ls.astype(dt))
        v_q, _ = refgs.covariance_3d_backward(fwd, (v_cov * v_scale).astype(dt))
    tol = 1e-6 if dt == np.float32 else 1e-14
    # |q| itself is returned in the dtype: for a subnormal |q| it carries the subnormal spacing
    tol_norm = max(tol, 4 * float(np.finfo(dt).smallest_subnormal) / norm)
    assert u.dtype == dt and np.all(np.isfinite(u))
    assert np.allclose(np.linalg.norm(u.astype(float), axis=1), 1, atol=tol)
    assert np.allclose(u, u_ref, atol=tol)
    assert np.allclose(np.ldexp(qn.astype(float), k2), np.linalg.norm(q64, axis=1), rtol=tol_norm)
    ref = refgs.covariance_3d(u_ref, ls)
    assert np.allclose(fwd["R"], ref["R"], atol=tol)
    # gradient: finite, orthogonal to q, and |q| * v_q independent of the scale
    v_ref, _ = refgs.covariance_3d_backward(ref, v_cov)
    v_q = v_q.astype(float)
    assert np.all(np.isfinite(v_q))
    assert np.allclose(np.sum(v_q * u_ref, axis=1), 0, atol=tol * np.max(np.abs(v_q)))
    ratio = np.ldexp(np.linalg.norm(q64, axis=1), -k2)[:, None] / v_scale
    assert np.allclose(v_q * ratio, v_ref, rtol=10 * tol_norm, atol=10 * tol_norm)
    if dt == np.float64 and norm == 1.0:
        # q and -q are the same rotation; q = 0 is an error naming the field and the row
        assert np.allclose(refgs.covariance_3d(-q, ls)["cov3d"], refgs.covariance_3d(q, ls)["cov3d"],
                           atol=1e-15)
        g = Gaussians(np.zeros((2, 3)) + [0, 0, 3], ls[:2], np.array([[1.0, 0, 0, 0], [0, 0, 0, 0]]),
                      np.zeros(2), np.zeros((2, 1, 3)))
        with pytest.raises(ValueError, match=r"Gaussians\.quats.*row 1"):
            render(g, identity_camera())


def test_cnv06_scale_activation():
    """CNV-06: s = exp(log_scales): eigenvalues of Sigma are s^2; on-axis 2D variance (f s / z)^2 + 0.3."""
    rng = np.random.default_rng(6)
    ls = rng.uniform(-4, 1, (5, 3))
    q = rng.normal(size=(5, 4))
    cov = refgs.covariance_3d(q, ls)["cov3d"]
    assert np.allclose(np.sort(np.linalg.eigvalsh(cov), axis=1), np.sort(np.exp(2 * ls), axis=1),
                       rtol=1e-12, atol=1e-15)
    # unrotated Gaussian straight ahead: the variances seen by the camera, no floor or ceiling
    cam = identity_camera(fx=30.0, fy=20.0)
    for lsx, lsy in [(math.log(0.07), math.log(0.11)), (-30.0, -25.0)]:
        out = render(one_gaussian((0, 0, Z), (lsx, lsy, math.log(0.2))), cam)
        a, b, c = out.cov2d[0]
        assert a == pytest.approx((30.0 * math.exp(lsx) / Z) ** 2 + 0.3, rel=1e-13)
        assert c == pytest.approx((20.0 * math.exp(lsy) / Z) ** 2 + 0.3, rel=1e-13)
        assert b == 0
    # d s / d log s = s: the log-scale gradient of a quadratic in Sigma
    fwd = refgs.covariance_3d(q, ls)
    v = rng.normal(size=(5, 3, 3))
    _, v_ls = refgs.covariance_3d_backward(fwd, v)
    h = 1e-6
    for i, k in [(0, 0), (3, 2)]:
        lp, lm = ls.copy(), ls.copy()
        lp[i, k] += h
        lm[i, k] -= h
        fd = (np.sum(v * refgs.covariance_3d(q, lp)["cov3d"])
              - np.sum(v * refgs.covariance_3d(q, lm)["cov3d"])) / (2 * h)
        assert v_ls[i, k] == pytest.approx(fd, rel=1e-7, abs=1e-12)


def test_cnv07_opacity_sigmoid():
    """CNV-07: o = 1 / (1 + exp(-l)) without overflow for any finite l; d o / d l = o (1 - o)."""
    logits = np.array([-1000.0, -30.0, -2.0, 0.0, 0.5, 3.0, 30.0, 1000.0])
    n = logits.size
    g = Gaussians(np.tile([0.0, 0.0, 3.0], (n, 1)) + np.linspace(-1, 1, n)[:, None] * [1, 0, 0],
                  np.full((n, 3), math.log(0.05)), np.tile([1.0, 0, 0, 0], (n, 1)), logits,
                  np.zeros((n, 1, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = render(g, identity_camera(), RenderConfig(profile="inria"))
    expected = np.array([1 / (1 + math.exp(-x)) if x > -700 else 0.0 for x in logits])
    assert np.allclose(out.opacities, expected, rtol=1e-15, atol=0)
    assert out.opacities[0] == 0.0 and out.opacities[-1] == 1.0
    # gradient: d L / d logit = (d L / d o) o (1 - o) -- compare with a difference in the logit
    cam = identity_camera()
    g1 = one_gaussian((1 / 32, 1 / 32, Z), logit=0.8)
    v = np.random.default_rng(7).normal(size=(H, W, 3))
    gr = render_backward(render(g1, cam), v)
    h = 1e-5

    def loss(l):
        return float(np.sum(v * render(g1.replace(opacity_logits=np.array([l])), cam).image))
    fd = (loss(0.8 + h) - loss(0.8 - h)) / (2 * h)
    assert gr.opacity_logits[0] == pytest.approx(fd, rel=1e-8)


def test_cnv08_pixel_centres():
    """CNV-08: pixel (i, j) is sampled at (j + 0.5, i + 0.5); u = fx x / z + cx; for cx = W/2 this
    is the original's integer-centre rule u' = fx x / z + W/2 - 0.5 at (j, i)."""
    cam = identity_camera()
    # fx x / z = 32 * (1/32) / 2 = 0.5 exactly: u = W/2 + 0.5 = 16.5, the centre of column 16
    x, y = 1 / 32, -3 / 32                      # v = 12 - 1.5 = 10.5: centre of row 10
    g = one_gaussian((x, y, Z), (math.log(0.12), math.log(0.2), math.log(0.1)),
                     quat=(math.cos(0.3), 0, 0, math.sin(0.3)), logit=1.0)
    out = render(g, cam)
    assert out.means2d[0].tolist() == [16.5, 10.5]
    i0, j0 = 10, 16
    assert np.unravel_index(np.argmax(out.alpha), out.alpha.shape) == (i0, j0)
    assert out.alpha[i0, j0] == pytest.approx(1 / (1 + math.exp(-1.0)), rel=1e-15)
    # point symmetry about the sampled centre: (i0 + di, j0 + dj) and (i0 - di, j0 - dj) agree
    # exactly (the Gaussian is rotated, so this also exercises the off-diagonal term)
    for di in range(-3, 4):
        for dj in range(-3, 4):
            assert out.alpha[i0 + di, j0 + dj] == out.alpha[i0 - di, j0 - dj]
    assert out.alpha[i0, j0 + 1] != out.alpha[i0 + 1, j0]           # anisotropic: not trivial
    # the original's rule, evaluated independently at integer pixel coordinates
    up = F * x / Z + W / 2 - 0.5
    vp = F * y / Z + H / 2 - 0.5
    A, B, C = out.conics[0]
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    dx, dy = up - jj, vp - ii
    a = np.minimum(0.99, out.opacities[0] * np.exp(-0.5 * (A * dx ** 2 + C * dy ** 2) - B * dx * dy))
    a = np.where(a >= 1 / 255, a, 0)
    assert np.allclose(out.alpha, a, rtol=0, atol=1e-15)
    # off-centre principal point: the same offset rule with cx, cy
    cam2 = identity_camera(cx=11.25, cy=14.75)
    out2 = render(g, cam2)
    assert np.allclose(out2.means2d[0], [F * x / Z + 11.25, F * y / Z + 14.75], atol=1e-14)


def _real_sh_cs(l, m, dirs):
    """Real SH with the Condon-Shortley phase from scipy's complex Y_l^m (an independent form)."""
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * np.pi)
    Y = sp.sph_harm_y(l, abs(m), theta, phi)
    if m > 0:
        return math.sqrt(2) * Y.real
    if m < 0:
        return math.sqrt(2) * Y.imag
    return Y.real


def test_cnv09_sh_basis():
    """CNV-09: basis k = l^2 + l + m is the real SH (Condon-Shortley phase) of degree l, order m;
    orthonormal on the sphere; the constants are the closed forms of the table."""
    rng = np.random.default_rng(9)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    basis, _ = refgs.sh_basis(3, d)
    for l in range(4):
        for m in range(-l, l + 1):
            assert np.allclose(basis[:, l * l + l + m], _real_sh_cs(l, m, d), atol=1e-14), (l, m)
    # closed-form constants
    sq = math.sqrt(math.pi)
    assert refgs.constants.SH_C0 == pytest.approx(1 / (2 * sq), rel=1e-15)
    assert refgs.constants.SH_C1 == pytest.approx(math.sqrt(3) / (2 * sq), rel=1e-15)
    assert refgs.constants.SH_C2[0] == pytest.approx(math.sqrt(15) / (2 * sq), rel=1e-15)
    assert refgs.constants.SH_C2[2] == pytest.approx(math.sqrt(5) / (4 * sq), rel=1e-15)
    assert refgs.constants.SH_C3[0] == pytest.approx(-math.sqrt(70) / (8 * sq), rel=1e-15)
    assert refgs.constants.SH_C3[1] == pytest.approx(math.sqrt(105) / (2 * sq), rel=1e-15)
    # orthonormality by Gauss-Legendre (cos theta) x trapezoid (phi) quadrature, exact for the
    # degree-6 products involved
    xg, wg = np.polynomial.legendre.leggauss(8)
    nphi = 16
    phi = 2 * np.pi * np.arange(nphi) / nphi
    ct, ph = np.meshgrid(xg, phi, indexing="ij")
    st_ = np.sqrt(1 - ct ** 2)
    dirs = np.stack([st_ * np.cos(ph), st_ * np.sin(ph), ct], -1).reshape(-1, 3)
    w = (wg[:, None] * np.full(nphi, 2 * np.pi / nphi)[None, :]).ravel()
    b, _ = refgs.sh_basis(3, dirs)
    gram = (b * w[:, None]).T @ b
    assert np.allclose(gram, np.eye(16), atol=1e-13)
    # the minus signs of the table (odd m) distinguish it from the no-phase real SH
    assert np.allclose(basis[:, 1], -refgs.constants.SH_C1 * d[:, 1], atol=1e-15)
    assert np.allclose(basis[:, 3], -refgs.constants.SH_C1 * d[:, 0], atol=1e-15)


def test_cnv10_colour_offset_clamp():
    """CNV-10: colour = max(sum_k b_k sh_k + 0.5, 0): no upper clamp, clamped channels pass no
    gradient, the rendered image is not clamped either."""
    rgb = np.array([-0.2, 0.3, 1.7])
    means = np.array([[0.0, 0.0, 3.0]])
    sh = np.zeros((1, 4, 3))
    sh[0, 0] = (rgb - 0.5) / SH_C0
    campos = np.zeros(3)
    fwd = refgs.eval_sh_colors(means, sh, campos, 0)
    assert np.allclose(fwd["colors"][0], [0.0, 0.3, 1.7], atol=1e-15)
    assert fwd["clamped"][0].tolist() == [True, False, False]
    # an all-zero SH vector is mid-grey
    assert np.allclose(refgs.eval_sh_colors(means, np.zeros((1, 1, 3)), campos, 0)["colors"], 0.5)
    # degree 1 along the view direction +z: rgb = C0 sh0 + C1 z sh2 + 0.5
    sh[0, 2] = [0.1, -0.2, 0.3]
    fwd1 = refgs.eval_sh_colors(means, sh, campos, 1)
    expect = rgb + refgs.constants.SH_C1 * sh[0, 2]
    assert np.allclose(fwd1["colors"][0], np.maximum(expect, 0), atol=1e-15)
    v_sh, _ = refgs.eval_sh_colors_backward(fwd1, sh, np.ones((1, 3)))
    assert np.all(v_sh[0, :, 0] == 0)                    # clamped channel: no gradient
    assert np.allclose(v_sh[0, :4, 1], fwd1["basis"][0])  # live channel: d colour / d sh = basis
    # the image is not clamped: a bright opaque Gaussian on a pixel centre exceeds 1
    g = one_gaussian((1 / 32, 1 / 32, Z), logit=8.0, rgb=(1.7, 1.7, 1.7))
    out = render(g, identity_camera())
    assert out.image.max() == pytest.approx(0.99 * 1.7, rel=1e-12) and out.image.max() > 1


def _float_arrays(obj, prefix=""):
    """(name, array) for every floating array in a RenderOutput/Gradients/cache, recursively."""
    items = obj.items() if isinstance(obj, dict) else ((k, getattr(obj, k)) for k in vars(obj))
    for k, v in items:
        if isinstance(v, dict):
            yield from _float_arrays(v, prefix + k + ".")
        elif isinstance(v, np.ndarray) and v.dtype.kind == "f":
            yield prefix + k, v


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_cnv11_dtype(dtype, profile):
    """CNV-11: the Gaussians' dtype is the working dtype of every floating output and gradient;
    integer outputs are integers; mixing float32 and float64 fields is a ValueError."""
    dt = np.dtype(dtype)
    rng = np.random.default_rng(11)
    cam = make_camera(rng, W, H)
    g = place_gaussians(rng, cam, 4, sh_degree=2).astype(dt)
    cfg = RenderConfig(profile=profile, background=(0.2, 0.3, 0.4),
                       antialiased=profile == "gsplat", opacity_scale=np.full(4, 0.9))
    out = render(g, cam, cfg)
    for name in ("image", "alpha", "depth", "means2d", "depths", "conics", "cov2d", "colors",
                 "opacities", "final_T"):
        assert getattr(out, name).dtype == dt, name
    assert out.radii.dtype.kind == "i" and out.n_contrib.dtype.kind == "i"
    assert out.visible.dtype == bool
    for name, arr in _float_arrays(out.cache):
        assert arr.dtype == dt, f"cache {name} is {arr.dtype}"
    v = rng.normal(size=(H, W, 3))                      # float64 cotangents are converted
    grads = render_backward(out, v, rng.normal(size=(H, W)), rng.normal(size=(H, W)))
    for name, arr in grads.to_dict().items():
        assert arr.dtype == dt and np.all(np.isfinite(arr)), name
    # float32 and float64 renders agree to float32 accuracy
    if dt == np.float32:
        ref = render(g.astype(np.float64), cam, cfg)
        assert np.allclose(out.image, ref.image, atol=2e-5)
    # integer arrays become float64 in the container; a float32/float64 mix is rejected
    gi = Gaussians(np.array([[0, 0, 3]]), np.array([[-2, -2, -2]]), np.array([[1, 0, 0, 0]]),
                   np.array([0]), np.zeros((1, 1, 3), np.int64))
    assert all(getattr(gi, f).dtype == np.float64 for f in Gaussians.FIELDS)
    mixed = g.replace(sh=g.sh.astype(np.float64 if dt == np.float32 else np.float32))
    with pytest.raises(ValueError, match="Gaussians"):
        render(mixed, cam, cfg)
