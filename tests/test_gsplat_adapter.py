"""gsplat 1.5.3's pure-torch stage functions against refgs' stages (profile "gsplat").

Covariance (COV-01), projection (PRJ-01..PRJ-05, PRJ-08: means2d, conics, depths, compensation,
radii) and SH colours (SH-01..SH-03, CNV-10) on random in-frustum scenes, in float32 (gsplat's
dtype) and float64 (where the agreement must be at round-off, which pins the formulas), plus
refgs' hand-derived projection backward against autograd through gsplat's projection (PRJ-07).
The reference is always refgs in float64.  ``python tests/test_gsplat_adapter.py`` prints the
measured errors recorded in docs/agreement.md.
"""
from __future__ import annotations

import numpy as np
import pytest

gsplat = pytest.importorskip("gsplat")
torch = pytest.importorskip("torch")

import refgs  # noqa: E402
from refgs.constants import GSPLAT  # noqa: E402
from refgs.projection import project_gaussians, project_gaussians_backward  # noqa: E402
from refgs.sh import eval_sh_colors  # noqa: E402
from oracle.adapters import gsplat_backend as gb  # noqa: E402
from gsplat.cuda import _torch_impl as gs  # noqa: E402

pytestmark = pytest.mark.gsplat

W, H = 64, 48
#: tolerances: float64 = round-off (pins the formulas; gsplat's SH constants carry ~15 digits);
#: float32 = float32 eps 1.2e-7 times the conditioning of each stage, about 10x the worst
#: measured over 40 scenes x 200 Gaussians (docs/agreement.md).
TOL = {
    # stage          float64   float32
    "cov_rel":      (1e-14, 1e-5),    # max |dSigma| / max |Sigma| per Gaussian
    "means2d_abs":  (1e-11, 5e-4),    # pixels (|means2d| up to a few hundred px)
    "depths_abs":   (1e-13, 5e-6),
    "conics_rel":   (1e-12, 1e-4),    # per Gaussian, relative to max |conic|
    "comp_abs":     (1e-13, 5e-5),
    "sh_abs":       (1e-13, 5e-6),
}
DTYPES = ("float64", "float32")


def scene(rng: np.random.Generator, n: int = 200):
    """N Gaussians around the origin, a camera ~4 units away looking at it (all well beyond the
    near plane); the principal point is off-centre so gsplat's asymmetric clamp matters."""
    eye = rng.normal(0, 0.6, 3) + np.array([0.0, 0.0, -4.0])
    cam = refgs.Camera.look_at(eye, rng.normal(0, 0.2, 3), fx=60.0, width=W, height=H,
                               cx=W / 2 + rng.uniform(-3, 3), cy=H / 2 + rng.uniform(-3, 3))
    g = refgs.Gaussians(rng.normal(0, 0.8, (n, 3)), rng.normal(-2.0, 0.8, (n, 3)),
                        rng.normal(size=(n, 4)), rng.normal(0, 2, n), rng.normal(0, 0.4, (n, 16, 3)))
    return g, cam


def measure(rng: np.random.Generator, dtype: str) -> dict:
    """Worst errors of gsplat's stages (``dtype``) against refgs (float64) on one scene."""
    g, cam = scene(rng)
    n = len(g)
    cov = refgs.covariance_3d(g.quats, g.log_scales)["cov3d"]
    cov_gs = gb.covariance_3d(g.quats, g.log_scales, dtype)
    e = {"cov_rel": np.max(np.abs(cov_gs - cov) / np.max(np.abs(cov), axis=(1, 2), keepdims=True))}
    ref = project_gaussians(g.means, cov, np.ones(n), cam, GSPLAT, antialiased=True)
    got = gb.project_gaussians(g.means, cov, cam, antialiased=True, dtype=dtype)
    v = ref["visible"]
    assert v.sum() > 0.8 * n
    e["means2d_abs"] = np.max(np.abs(got["means2d"] - ref["means2d"])[v])
    e["depths_abs"] = np.max(np.abs(got["depths"] - ref["depths"]))
    e["conics_rel"] = np.max(np.abs(got["conics"] - ref["conics"])[v]
                             / np.max(np.abs(ref["conics"][v]), axis=1, keepdims=True))
    e["comp_abs"] = np.max(np.abs(got["comp"] - ref["comp"])[v])
    e["sh_abs"] = max(np.max(np.abs(gb.eval_sh_colors(g.means, g.sh, cam.center, d, dtype)
                                    - eval_sh_colors(g.means, g.sh, cam.center, d)["colors"]))
                      for d in range(4))
    return {k: float(x) for k, x in e.items()}


@pytest.mark.parametrize("dtype", DTYPES)
def test_stages_match_refgs(dtype):
    rng = np.random.default_rng(2024)
    col = DTYPES.index(dtype)
    for _ in range(3):
        for name, err in measure(rng, dtype).items():
            assert err <= TOL[name][col], f"{name} ({dtype}): {err:.3e} > {TOL[name][col]:.0e}"


def test_covariance_dtype_and_shape():
    rng = np.random.default_rng(0)
    g, _ = scene(rng, 7)
    for dtype, np_dtype in (("float32", np.float32), ("float64", np.float64)):
        cov = gb.covariance_3d(g.quats, g.log_scales, dtype)
        assert cov.shape == (7, 3, 3) and cov.dtype == np_dtype
    with pytest.raises(ValueError, match="dtype"):
        gb.covariance_3d(g.quats, g.log_scales, "float16")


def test_radius_rule_difference():
    """gsplat's torch radius is ceil(3.33 sqrt(Sigma_ii)); the CUDA kernel (and refgs' gsplat
    profile) uses extend = min(3.33, sqrt(2 ln(255 o))) < 3.33 for o < 1 and culls o < 1/255.
    At o = 1 the two differ by at most one pixel; faint Gaussians get much smaller CUDA radii."""
    rng = np.random.default_rng(5)
    g, cam = scene(rng)
    n = len(g)
    cov = refgs.covariance_3d(g.quats, g.log_scales)["cov3d"]
    got = gb.project_gaussians(g.means, cov, cam, dtype="float64")["radii"]
    ref = project_gaussians(g.means, cov, np.ones(n), cam, GSPLAT)
    v = ref["visible"]
    np.testing.assert_array_equal(got[~v], 0)
    d = got[v] - ref["radii"][v]
    assert d.min() >= 0 and d.max() <= 1
    faint = project_gaussians(g.means, cov, np.full(n, 0.02), cam, GSPLAT)["radii"]
    assert np.all(faint[v] <= ref["radii"][v]) and np.mean(faint[v] < got[v]) > 0.9
    culled = project_gaussians(g.means, cov, np.full(n, 0.5 / 255), cam, GSPLAT)
    assert not culled["visible"].any()


def test_tiny_quaternion_difference():
    """gsplat's ``_quat_to_rotmat`` normalises with F.normalize (eps 1e-12): a quaternion with
    |q| < 1e-12 is divided by 1e-12, not |q|, so R is not a rotation and Sigma is wrong; refgs
    divides by max|q_k| first (CNV-05, HARD-06).  Above 1e-12 the two agree."""
    q = np.array([[0.3, -0.5, 0.7, 0.2]])
    ls = np.log([[0.5, 0.2, 0.1]])
    for s, same in ((1.0, True), (1e-11, True), (1e-13, False), (1e-22, False)):
        got = gb.covariance_3d(q * s, ls, "float64")
        ref = refgs.covariance_3d(q * s, ls)["cov3d"]
        assert (np.max(np.abs(got - ref)) < 1e-15) == same, s


def test_near_plane_difference():
    """At exactly z = near the pure-torch projection culls (z > near strict); CUDA and refgs keep."""
    cam = refgs.Camera(np.eye(4), np.array([[40.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]]), W, H)
    means = np.array([[0.0, 0.0, gb.NEAR], [0.0, 0.0, 0.5]])
    cov = np.tile(np.eye(3) * 1e-4, (2, 1, 1))
    got = gb.project_gaussians(means, cov, cam, dtype="float64")
    ref = project_gaussians(means, cov, np.ones(2), cam, GSPLAT)
    assert ref["visible"].tolist() == [True, True]
    assert got["radii"][:, 0].tolist()[0] == 0 and got["radii"][1, 0] > 0


def test_projection_backward_matches_gsplat_autograd():
    """refgs' hand-derived projection backward (PRJ-07, RAS-08 conic convention, PRJ-08
    compensation) against autograd through gsplat's pure-torch projection, float64, including
    Gaussians beyond the frustum clamp (exact depth term under the clamp)."""
    rng = np.random.default_rng(17)
    g, cam = scene(rng, 60)
    means = g.means.copy()
    t = means @ cam.rotation.T + cam.translation
    means[:10] += 1.5 * t[:10, 2, None] * cam.rotation[0]    # camera x += 1.5 z: beyond the clamp
    log_scales = g.log_scales.copy()
    log_scales[:10] = np.log(rng.uniform(1.0, 2.0, (10, 3)))      # big enough to reach the image
    cov = refgs.covariance_3d(g.quats, log_scales)["cov3d"]
    fwd = project_gaussians(means, cov, np.ones(len(g)), cam, GSPLAT, antialiased=True)
    tc = fwd["t"]
    clamped = np.abs(tc[:, 0] / tc[:, 2]) > (W - cam.cx) / cam.fx + 0.3 * 0.5 * W / cam.fx
    assert clamped[:10].all() and fwd["visible"][:10].sum() >= 5
    vis = fwd["visible"]
    vm, vc, vd, vk = (rng.normal(size=s) for s in ((len(g), 2), (len(g), 3), (len(g),), (len(g),)))
    v_means, v_cov = project_gaussians_backward(fwd, cam, vm, vc, vd, vk)

    m_t = torch.tensor(means, requires_grad=True)
    c_t = torch.tensor(cov, requires_grad=True)
    _, m2d, dep, con, comp = gs._fully_fused_projection(
        m_t, c_t, torch.tensor(np.asarray(cam.world_to_camera, float))[None],
        torch.tensor(np.asarray(cam.K, float))[None], W, H, eps2d=gb.EPS2D,
        near_plane=gb.NEAR, far_plane=gb.FAR, calc_compensations=True)
    mask = torch.tensor(vis.astype(float))
    loss = ((m2d[0] * torch.tensor(vm)).sum(-1) + (con[0] * torch.tensor(vc)).sum(-1)
            + dep[0] * torch.tensor(vd) + comp[0] * torch.tensor(vk))
    gm, gc = torch.autograd.grad((loss * mask).sum(), [m_t, c_t])
    gm, gc = gm.numpy(), gc.numpy()
    sym = lambda x: 0.5 * (x + np.swapaxes(x, -1, -2))  # noqa: E731
    for a, b in ((v_means[vis], gm[vis]), (sym(v_cov)[vis], sym(gc)[vis])):
        rel = np.linalg.norm(a - b) / np.linalg.norm(b)
        assert rel <= 1e-10, rel
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-10 * np.abs(b).max())


def test_backend_object():
    b = gb.gsplat_backend
    assert (b.name, b.version, b.profile, b.dtype, b.max_sh_degree) == \
        ("gsplat", "1.5.3", "gsplat", "float32", 3)
    rng = np.random.default_rng(3)
    g, cam = scene(rng, 5)
    if torch.cuda.is_available():
        assert b.unavailable_reason is None and b.has_backward
    else:
        assert "CUDA" in b.unavailable_reason and not b.has_backward
        with pytest.raises(gb.BackendUnavailable, match="CUDA"):
            b.render(g, cam, refgs.RenderConfig(profile="gsplat"))
    assert b.stage_covariance(g.quats, g.log_scales).dtype == np.float32
    proj = b.stage_projection(g.means, refgs.covariance_3d(g.quats, g.log_scales)["cov3d"], np.ones(5),
                              cam, refgs.RenderConfig(profile="gsplat"))
    assert proj["means2d"].shape == (5, 2) and proj["visible"].dtype == bool
    assert b.stage_sh(g.means, g.sh, cam.center, 3).shape == (5, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat.rasterization needs CUDA")
def test_cuda_render_matches_refgs():  # pragma: no cover - not run on the CPU dev machine
    """gsplat.rasterization (float32, CUDA) against refgs' gsplat profile in float64.  The
    tolerances are provisional (written without a GPU to measure on): float32 with __expf."""
    rng = np.random.default_rng(8)
    g, cam = scene(rng, 100)
    cfg = refgs.RenderConfig(profile="gsplat", background=(0.2, 0.4, 0.6), sh_degree=3)
    ref = refgs.render(g, cam, cfg)
    out = gb.gsplat_backend.render(g, cam, cfg)
    np.testing.assert_allclose(out.image, ref.image, atol=1e-3)
    np.testing.assert_allclose(out.alpha, ref.alpha, atol=1e-3)
    np.testing.assert_allclose(out.depth, ref.depth, atol=1e-2)
    np.testing.assert_array_equal(out.radii > 0, ref.radii > 0)
    v = rng.normal(size=ref.image.shape)
    gr, go = refgs.render_backward(ref, v), gb.gsplat_backend.render_backward(out, v)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d"):
        a, b = getattr(go, name), getattr(gr, name)
        assert np.linalg.norm(a - b) <= 1e-2 * np.linalg.norm(b), name


if __name__ == "__main__":
    # measured worst errors over 40 scenes of 200 Gaussians (the table in docs/agreement.md)
    for dtype in DTYPES:
        rng = np.random.default_rng(0)
        worst: dict = {}
        for _ in range(40):
            for k, x in measure(rng, dtype).items():
                worst[k] = max(worst.get(k, 0.0), x)
        print(dtype, {k: f"{x:.1e}" for k, x in worst.items()})
