"""Input validation and the public containers (API-01 .. API-06, CNV-02, CNV-03, CNV-05, SH-01,
PRJ-08): every bad input raises ValueError with a one-line message naming the field."""
from __future__ import annotations

import math
from dataclasses import FrozenInstanceError, replace

import numpy as np
import pytest

import refgs
from refgs import Camera, Gaussians, Gradients, RenderConfig, RenderOutput, render, render_backward
from refgs.constants import SH_C0

W, H = 24, 16
N, K = 3, 4


def camera(**changes) -> Camera:
    K_ = np.array([[20.0, 0, 12], [0, 20.0, 8], [0, 0, 1]])
    cam = Camera(np.eye(4), K_, W, H)
    return replace(cam, **changes) if changes else cam


def gaussians(dtype=np.float64, n=N, k=K) -> Gaussians:
    rng = np.random.default_rng(0)
    means = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n), rng.uniform(2, 3, n)], -1)
    sh = 0.1 * rng.normal(size=(n, k, 3))
    sh[:, 0] = (0.6 - 0.5) / SH_C0
    return Gaussians(means, np.full((n, 3), math.log(0.1)), rng.normal(size=(n, 4)),
                     np.zeros(n), sh).astype(dtype)


def expect_error(field: str, g=None, cam=None, cfg=None):
    """render(...) must raise ValueError whose single-line message names ``field``."""
    with pytest.raises(ValueError) as info:
        render(gaussians() if g is None else g, camera() if cam is None else cam,
               RenderConfig() if cfg is None else cfg)
    msg = str(info.value)
    assert field in msg, msg
    assert "\n" not in msg and "expected" in msg, msg


def test_valid_inputs_render():
    """API-03 guard: the fixtures below are valid, so each error comes from the one field changed."""
    out = render(gaussians(), camera(), RenderConfig(profile="gsplat", antialiased=True,
                                                    opacity_scale=np.ones(N), sh_degree=1))
    assert out.visible.all()


# ------------------------------------------------------------------------------------------
# API-03: Gaussians
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("field,bad", [
    ("means", np.zeros((N, 4))), ("means", np.zeros(N)), ("means", np.zeros((N, 3, 1))),
    ("log_scales", np.zeros((N, 2))), ("log_scales", np.zeros((N + 1, 3))),
    ("quats", np.ones((N, 3))), ("quats", np.ones(4)),
    ("opacity_logits", np.zeros((N, 1))), ("opacity_logits", np.zeros(N + 1)),
    ("sh", np.zeros((N, K, 4))), ("sh", np.zeros((N, 0, 3))), ("sh", np.zeros((N + 1, K, 3))),
    ("sh", np.zeros((N, 3 * K))),
])
def test_wrong_shapes(field, bad):
    """API-03: wrong shapes name the field."""
    g = gaussians().replace(**{field: bad})
    expect_error("Gaussians." + field if field != "means" else "Gaussians.", g=g)


def test_mixed_dtypes():
    """API-03/CNV-11: a float32/float64 mix names the Gaussians fields."""
    for field in Gaussians.FIELDS:
        g = gaussians()
        g = g.replace(**{field: getattr(g, field).astype(np.float32)})
        expect_error("Gaussians", g=g)


@pytest.mark.parametrize("field", list(Gaussians.FIELDS))
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_non_finite(field, value, dtype):
    """API-03: NaN / Inf in any field (either dtype) names that field."""
    g = gaussians(dtype)
    arr = getattr(g, field).copy()
    arr.reshape(-1)[1] = value
    expect_error(f"Gaussians.{field}", g=g.replace(**{field: arr}))


def test_zero_and_tiny_quaternion():
    """CNV-05/API-03: an all-zero quaternion is rejected (naming the row); a tiny one is not."""
    g = gaussians()
    q = g.quats.copy()
    q[2] = 0.0
    expect_error("Gaussians.quats", g=g.replace(quats=q))
    with pytest.raises(ValueError, match="row 2"):
        render(g.replace(quats=q), camera())
    q[2] = [0.0, 1e-300, 0.0, 0.0]
    assert render(g.replace(quats=q), camera()).visible[2]
    q[2] = [0.0, -0.0, 0.0, 0.0]
    expect_error("Gaussians.quats", g=g.replace(quats=q))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_log_scale_overflow_limit(dtype):
    """API-03: log-scales above LOG_SCALE_MAX_FRACTION * ln(max float) are rejected."""
    lim = refgs.constants.LOG_SCALE_MAX_FRACTION * np.log(np.finfo(dtype).max)
    g = gaussians(dtype)
    ls = g.log_scales.copy()
    ls[0, 1] = lim + 0.5
    expect_error("Gaussians.log_scales", g=g.replace(log_scales=ls))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_accepted_log_scales_do_not_overflow(dtype, profile):
    """API-03/HARD-11: every log-scale validation accepts renders and differentiates without
    overflow: no warning, finite outputs and gradients, radii >= 0, the Gaussian visible."""
    import warnings
    lim = refgs.constants.LOG_SCALE_MAX_FRACTION * np.log(np.finfo(dtype).max)
    for ls_value in (0.5 * lim, 0.8 * lim, lim - 1):
        g = gaussians(dtype, n=1)
        g = g.replace(log_scales=np.full((1, 3), ls_value, dtype) - np.array([0, 0.5, 1], dtype))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            out = render(g, camera(), RenderConfig(profile=profile))
            gr = render_backward(out, np.ones((H, W, 3)))
        assert out.visible[0] and np.all(out.radii >= 0), ls_value
        assert all(np.all(np.isfinite(a)) for a in gr.to_dict().values()), ls_value


# ------------------------------------------------------------------------------------------
# API-03: Camera (CNV-02, CNV-03)
# ------------------------------------------------------------------------------------------

def _rigid(R, t=(0.1, -0.2, 0.3)):
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = t
    return E


@pytest.mark.parametrize("name,E", [
    ("scale", _rigid(1.01 * np.eye(3))),
    ("shear", _rigid(np.array([[1.0, 0.05, 0], [0, 1, 0], [0, 0, 1]]))),
    ("reflection", _rigid(np.diag([1.0, 1.0, -1.0]))),
    ("bottom row", np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 2]])),
    ("bottom row 2", np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0, 0, 1]])),
    ("nan", _rigid(np.eye(3), (np.nan, 0, 0))),
    ("inf", _rigid(np.eye(3), (0, np.inf, 0))),
    ("shape", np.eye(4)[:3]),
    ("shape 3x3", np.eye(3)),
])
def test_non_rigid_world_to_camera(name, E):
    """CNV-02/API-03: scale, shear, reflection, a bad bottom row, non-finite entries or a wrong
    shape name Camera.world_to_camera."""
    expect_error("Camera.world_to_camera", cam=camera(world_to_camera=E))


def test_rigid_tolerance():
    """CNV-02: a rotation off by less than RIGID_TOL (float32 COLMAP poses) is accepted."""
    R = np.eye(3)
    R[0, 1] = 3e-5
    render(gaussians(), camera(world_to_camera=_rigid(R)))
    R[0, 1] = 3e-4
    expect_error("Camera.world_to_camera", cam=camera(world_to_camera=_rigid(R)))


@pytest.mark.parametrize("entry,value", [((0, 0), 0.0), ((0, 0), -20.0), ((1, 1), 0.0),
                                         ((1, 1), -1e-9), ((0, 2), np.nan), ((1, 2), np.inf),
                                         ((0, 0), np.nan)])
def test_bad_intrinsics(entry, value):
    """CNV-03/API-03: fx, fy <= 0 or non-finite K name Camera.K."""
    K_ = camera().K.copy()
    K_[entry] = value
    expect_error("Camera.K", cam=camera(K=K_))


def test_bad_intrinsics_shape_and_size():
    """CNV-03/API-03: K not 3 x 3; width/height non-positive or non-integer."""
    expect_error("Camera.K", cam=camera(K=np.eye(2)))
    for name in ("width", "height"):
        for bad in (0, -4, 16.0, 2.5, "16"):
            expect_error(f"Camera.{name}", cam=camera(**{name: bad}))


def test_wrong_argument_types():
    """API-03: non-Gaussians / Camera / RenderConfig arguments are named."""
    with pytest.raises(ValueError, match="gaussians"):
        render(gaussians().to_dict(), camera())
    with pytest.raises(ValueError, match="camera"):
        render(gaussians(), (np.eye(4), camera().K, W, H))
    with pytest.raises(ValueError, match="config"):
        render(gaussians(), camera(), {"profile": "inria"})


# ------------------------------------------------------------------------------------------
# API-02/API-03: RenderConfig
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("bg", [(0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (np.nan, 0.0, 0.0),
                                (0.0, np.inf, 0.0), None, ((0.0, 0.0, 0.0),)])
def test_bad_background(bg):
    """RAS-06/API-03: the background must be 3 finite values."""
    expect_error("RenderConfig.background", cfg=RenderConfig(background=bg))


@pytest.mark.parametrize("field,kwargs", [
    ("RenderConfig.background", {"cfg": RenderConfig(background="white")}),
    ("RenderConfig.background", {"cfg": RenderConfig(background=(1.0, "a", 0.0))}),
    ("Camera.K", {"cam": camera(K=[[20, 0, 12], [0, 20, 8], [0, 0, "x"]])}),
    ("RenderConfig.opacity_scale", {"cfg": RenderConfig(opacity_scale=[None, 1.0, 1.0])}),
])
def test_non_numeric_inputs_name_the_field(field, kwargs):
    """API-03: a non-numeric value is a ValueError naming the field, like any other bad value."""
    expect_error(field, **kwargs)


@pytest.mark.parametrize("deg", [1.5, "2", True])
def test_sh_degree_must_be_an_integer(deg):
    """SH-01/API-03: sh_degree is None or an integer 0..3."""
    with pytest.raises(ValueError, match="RenderConfig.sh_degree"):
        render(gaussians(k=16), camera(), RenderConfig(sh_degree=deg))


def test_sh_degree_rules():
    """SH-01/API-03: sh_degree outside 0..3, or more than K allows, is rejected."""
    for deg in (-1, 4, 7):
        expect_error("RenderConfig.sh_degree", cfg=RenderConfig(sh_degree=deg))
    # K = 4 carries degree 1: degree 2 or 3 needs more coefficients (names the field and degree)
    for deg in (2, 3):
        with pytest.raises(ValueError) as info:
            render(gaussians(k=4), camera(), RenderConfig(sh_degree=deg))
        assert "Gaussians.sh" in str(info.value) and "sh_degree" in str(info.value)
    render(gaussians(k=4), camera(), RenderConfig(sh_degree=0))
    render(gaussians(k=9), camera(), RenderConfig(sh_degree=2))


def test_profile_and_antialiased():
    """API-02/PRJ-08: an unknown profile names RenderConfig.profile; antialiased with the inria
    profile names RenderConfig.antialiased; a Profile instance is accepted."""
    expect_error("RenderConfig.profile", cfg=RenderConfig(profile="cuda"))
    expect_error("RenderConfig.profile", cfg=RenderConfig(profile=None))
    expect_error("RenderConfig.antialiased", cfg=RenderConfig(profile="inria", antialiased=True))
    out = render(gaussians(), camera(), RenderConfig(profile=refgs.GSPLAT, antialiased=True))
    assert out.cache["profile"] is refgs.GSPLAT


@pytest.mark.parametrize("scale", [np.ones(N + 1), np.ones((N, 1)), np.array([1.0, np.nan, 1.0]),
                                   np.array([1.0, -0.1, 1.0]), np.array([1.0, np.inf, 1.0]), 1.0])
def test_bad_opacity_scale(scale):
    """API-02/API-03: opacity_scale must be None or (N,) finite non-negative."""
    expect_error("RenderConfig.opacity_scale", cfg=RenderConfig(opacity_scale=scale))


def test_opacity_scale_zero_is_valid():
    """API-02: kappa = 0 is allowed and removes the Gaussian's contribution."""
    out = render(gaussians(), camera(), RenderConfig(opacity_scale=np.zeros(N)))
    assert np.all(out.alpha == 0)


# ------------------------------------------------------------------------------------------
# render_backward cotangents (API-05)
# ------------------------------------------------------------------------------------------

def test_bad_cotangents():
    """API-03/API-05: render_backward names v_image / v_alpha / v_depth on a wrong shape or a
    non-finite value; None v_image is rejected."""
    out = render(gaussians(), camera())
    good = np.ones((H, W, 3))
    for bad in (np.ones((H, W)), np.ones((W, H, 3)), np.ones((H, W, 4)), np.full((H, W, 3), np.nan)):
        with pytest.raises(ValueError, match="v_image"):
            render_backward(out, bad)
    with pytest.raises(ValueError, match="v_image"):
        render_backward(out, None)
    for name in ("v_alpha", "v_depth"):
        for bad in (np.ones((H, W, 1)), np.ones((W, H)), np.full((H, W), np.inf)):
            with pytest.raises(ValueError, match=name):
                render_backward(out, good, **{name: bad})


# ------------------------------------------------------------------------------------------
# API-01, API-04, API-05, API-06: containers and shapes
# ------------------------------------------------------------------------------------------

def test_gaussians_container():
    """API-01: a frozen plain container; float32/float64 kept, anything else float64; helpers."""
    g = gaussians()
    assert len(g) == N and g.dtype == np.float64
    assert len(Gaussians.empty(k=9)) == 0 and Gaussians.empty(k=9).sh.shape == (0, 9, 3)
    assert Gaussians.empty(dtype=np.float32).dtype == np.float32
    g32 = g.astype(np.float32)
    assert all(getattr(g32, f).dtype == np.float32 for f in Gaussians.FIELDS)
    sub = g.subset(np.array([True, False, True]))
    assert len(sub) == 2 and np.array_equal(sub.means, g.means[[0, 2]])
    assert np.array_equal(g.subset(np.array([1])).quats, g.quats[1:2])
    rep = g.replace(opacity_logits=np.ones(N))
    assert np.all(rep.opacity_logits == 1) and rep.means is g.means
    assert set(g.to_dict()) == set(Gaussians.FIELDS)
    gi = Gaussians([[0, 0, 1]], [[0, 0, 0]], [[1, 0, 0, 0]], [0], [[[0, 0, 0]]])
    assert all(getattr(gi, f).dtype == np.float64 for f in Gaussians.FIELDS)
    with pytest.raises(FrozenInstanceError):
        g.means = np.zeros((N, 3))
    # the container does not validate; render does
    bad = Gaussians(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((2, 4)), np.zeros(2), np.zeros((2, 1, 3)))
    with pytest.raises(ValueError):
        render(bad, camera())


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_render_output_and_gradient_shapes(dtype, profile):
    """API-04/API-05: RenderOutput and Gradients fields, shapes and dtypes; frozen."""
    g = gaussians(dtype, k=16)
    cfg = RenderConfig(profile=profile)
    out = render(g, camera(), cfg)
    assert isinstance(out, RenderOutput)
    shapes = {"image": (H, W, 3), "alpha": (H, W), "depth": (H, W), "n_contrib": (H, W),
              "final_T": (H, W), "radii": (N, 2), "means2d": (N, 2), "depths": (N,),
              "conics": (N, 3), "cov2d": (N, 3), "colors": (N, 3), "opacities": (N,),
              "visible": (N,)}
    for name, shape in shapes.items():
        assert getattr(out, name).shape == shape, name
    assert out.n_contrib.dtype == np.int32 and out.radii.dtype == np.int32
    assert out.gaussians is g and out.config is cfg
    if profile == "inria":
        assert np.array_equal(out.radii[:, 0], out.radii[:, 1])
    with pytest.raises(FrozenInstanceError):
        out.image = None
    gr = render_backward(out, np.ones((H, W, 3)))
    assert isinstance(gr, Gradients)
    expect = {"means": (N, 3), "log_scales": (N, 3), "quats": (N, 4), "opacity_logits": (N,),
              "sh": (N, 16, 3), "means2d": (N, 2)}
    for name, shape in expect.items():
        arr = getattr(gr, name)
        assert arr.shape == shape and arr.dtype == dtype, name
    assert set(gr.params()) == set(Gaussians.FIELDS)
    # the default degree for K = 16 is 3: every coefficient is live
    assert np.all(np.any(gr.sh != 0, axis=(0, 2)))


def test_validation_happens_before_work(monkeypatch):
    """API-03: render validates before computing anything (no stage runs on bad input)."""
    import sys
    render_mod = sys.modules["refgs.render"]
    calls = []
    monkeypatch.setattr(render_mod, "covariance_3d", lambda *a, **k: calls.append(1))
    with pytest.raises(ValueError):
        render(gaussians(), camera(), RenderConfig(background=(1.0, 2.0)))
    assert calls == []


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_empty_scene_api(profile):
    """API-06: N = 0 renders the background exactly, zero-row per-Gaussian outputs."""
    out = render(Gaussians.empty(k=4), camera(), RenderConfig(profile=profile, background=(0.1, 0.2, 0.3)))
    assert np.all(out.image == np.array([0.1, 0.2, 0.3])) and np.all(out.final_T == 1)
    for name in ("radii", "means2d", "conics", "cov2d", "colors"):
        assert getattr(out, name).shape[0] == 0, name
    gr = render_backward(out, np.ones((H, W, 3)))
    assert gr.sh.shape == (0, 4, 3)
