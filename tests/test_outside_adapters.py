"""Adapters for renderers written outside this project (docs/conformance.md): gswarp 1.1.0 and
taichi-splatting 0.13.0, each judged by the oracle's own evaluators and tolerance table
(ORC-01..ORC-05) on one tiny scene, plus the capabilities each adapter declares.  Skipped when the
package is not installed (optional extras ``gswarp`` and ``taichi``)."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

import refgs
from oracle import evaluate as ev
from oracle import tolerances as tl
from oracle.checks import CHECKS
from oracle.protocol import Case, describe_backend
from refgs.constants import get_profile
from refgs.deviations import apply_deviations

HAS_GSWARP = importlib.util.find_spec("gswarp") is not None
HAS_TAICHI = importlib.util.find_spec("taichi_splatting") is not None
needs_gswarp = pytest.mark.skipif(not HAS_GSWARP, reason="gswarp not installed (pip install 'refgs[gswarp]')")
needs_taichi = pytest.mark.skipif(not HAS_TAICHI,
                                  reason="taichi-splatting not installed (docs/conformance.md)")

#: taichi-splatting's conventions as refgs deviations (docs/conformance.md)
TAICHI_SH = frozenset({"sh_dir_reversed", "colour_clamp_01"})
TAICHI_PROJECTION = frozenset({"no_frustum_clamp", "radius_3sigma"})


def tiny_case(dtype: str, n: int = 4, seed: int = 0, opaque: bool = False, **cfg) -> Case:
    """N Gaussians well inside a 24 x 20 px view, off-centre principal point, degree-1 SH,
    rounded to ``dtype`` (ORC-05)."""
    rng = np.random.default_rng(seed)
    cam = refgs.Camera.look_at([0.2, -0.1, -3.0], [0, 0, 0], fx=30.0, fy=27.0, width=24, height=20,
                               cx=11.3, cy=10.6)
    logits = rng.uniform(6, 9, n) if opaque else rng.uniform(-1, 2, n)
    g = refgs.Gaussians(rng.normal(0, 0.25, (n, 3)), rng.uniform(-2.4, -1.6, (n, 3)),
                        rng.normal(size=(n, 4)), logits, rng.normal(0, 0.4, (n, 4, 3)))
    return Case(g, cam, refgs.RenderConfig(profile="inria", **cfg), seed=seed,
                label="tiny").rounded(dtype)


def context(backend) -> ev.Context:
    return ev.Context(describe_backend(backend, type(backend).__name__))


# ---- gswarp -------------------------------------------------------------------------------------


@needs_gswarp
def test_gswarp_declares_inria_float32_and_the_original_clamp_gradient():
    from oracle.adapters.gswarp_backend import gswarp_float32 as be

    info = describe_backend(be, "gswarp")
    assert (info.profile, info.dtype, info.max_sh_degree) == ("inria", "float32", 3)
    assert info.has_backward and info.unavailable_reason is None
    assert not info.supports_antialiased and info.supports_opacity_scale
    names = {c.name: c for c in CHECKS}
    assert {k["check"] for k in info.known_differences} == {"backward_frustum_clamp", "hard_01", "hard_05"}
    for k in info.known_differences:
        assert "PRJ-07" in names[k["check"]].clauses or k["check"] == "hard_05"
        assert k["link"].endswith("diff-gaussian-rasterization/issues/75")


@needs_gswarp
def test_gswarp_camera_matrices_put_refgs_pixel_centres_on_gswarp_pixels():
    """viewmatrix / projmatrix as gswarp reads them (row-vector layout, NDC to pixel
    ((v + 1) S - 1) / 2): gswarp's coordinate of a point is refgs' means2d - 0.5 (CNV-08)."""
    from oracle.adapters.gswarp_backend import camera_settings

    case = tiny_case("float64")
    cam = case.camera
    s = camera_settings(cam, (0, 0, 0), 1)
    m = np.asarray(case.gaussians.means)
    hom = np.c_[m, np.ones(len(m))] @ s.projmatrix.numpy().astype(np.float64)
    ndc = hom[:, :2] / hom[:, 3:]
    pix = ((ndc + 1) * [cam.width, cam.height] - 1) / 2
    ref = refgs.render(case.gaussians, cam, case.config)
    np.testing.assert_allclose(pix + 0.5, ref.means2d, atol=1e-4)      # float32 matrices
    z = np.c_[m, np.ones(len(m))] @ s.viewmatrix.numpy().astype(np.float64)[:, 2]
    np.testing.assert_allclose(z, ref.depths, rtol=1e-6)
    np.testing.assert_allclose(s.campos.numpy(), cam.center, atol=1e-6)


@needs_gswarp
def test_gswarp_forward_and_backward_match_refgs_within_the_oracle_tolerances():
    """One render and one backward of a tiny scene, judged by the oracle's evaluators (every
    output gswarp provides, every gradient field, the 2D-mean gradient in pixels)."""
    from oracle.adapters.gswarp_backend import gswarp_float32 as be

    ctx = context(be)
    case = tiny_case("float32", background=(0.2, 0.1, 0.4))
    fwd = ev.forward(ctx, case)
    assert fwd.ok, fwd.message()
    assert {"image", "alpha", "depth", "radii", "means2d", "conics"} <= fwd.provided
    bwd = ev.backward(ctx, case)
    assert bwd.ok, bwd.message()
    assert "grad:means2d" in bwd.provided


@needs_gswarp
def test_gswarp_rejects_invalid_input_with_value_error():
    from oracle.adapters.gswarp_backend import gswarp_float32 as be

    case = tiny_case("float32")
    g = case.gaussians
    bad = refgs.Gaussians(g.means, g.log_scales, np.zeros_like(g.quats), g.opacity_logits, g.sh)
    with pytest.raises(ValueError, match="quats"):
        be.render(bad, case.camera, case.config)
    with pytest.raises(ValueError, match="profile"):
        be.render(g, case.camera, refgs.RenderConfig(profile="gsplat"))


# ---- taichi-splatting ---------------------------------------------------------------------------


@needs_taichi
def test_taichi_declares_what_runs_here():
    from oracle.adapters import taichi_splatting_backend as tb

    for be in (tb.taichi_float32, tb.taichi_float64):
        info = describe_backend(be, "taichi")
        assert info.profile == "inria" and set(info.stages) == {"projection", "sh"}
        assert {k["check"] for k in info.known_differences} <= {"stage_sh", "stage_projection"}
    assert "float64" in tb.taichi_float64.unavailable_reason
    if not tb.CUDA:
        assert "CUDA" in tb.taichi_float32.unavailable_reason
        assert not tb.taichi_float32.has_backward
        case = tiny_case("float32")
        with pytest.raises(tb.BackendUnavailable, match="CUDA"):
            tb.taichi_float32.render(case.gaussians, case.camera, case.config)


@needs_taichi
def test_taichi_quaternion_order_and_covariance_factoring_round_trip():
    from oracle.adapters.taichi_splatting_backend import factor_covariance, wxyz_to_xyzw

    assert wxyz_to_xyzw(np.array([1.0, 2.0, 3.0, 4.0])).tolist() == [2.0, 3.0, 4.0, 1.0]
    case = tiny_case("float64", n=6, seed=3)
    g = case.gaussians
    cov = refgs.covariance_3d(g.quats, g.log_scales)["cov3d"]
    q, log_s = factor_covariance(cov)
    back = refgs.covariance_3d(q, log_s)["cov3d"]
    np.testing.assert_allclose(back, cov, rtol=0, atol=1e-14 * np.abs(cov).max())


@needs_taichi
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_taichi_sh_stage_is_refgs_with_its_sh_conventions(dtype):
    """evaluate_sh_at equals refgs' SH with the view direction reversed and the colour clamped
    to [0, 1] (SH-03, CNV-10) within the oracle's tolerance: the (N, 3, K) layout mapping."""
    from oracle.adapters import taichi_splatting_backend as tb

    be = tb.taichi_float32 if dtype == "float32" else tb.taichi_float64
    case = tiny_case(dtype, n=8, seed=1)
    g, cam = case.gaussians, case.camera
    campos = cam.center.astype(dtype).astype(np.float64)
    got = be.stage_sh(g.means, g.sh, campos, 1)
    prof = apply_deviations(get_profile("inria"), TAICHI_SH)
    exp = refgs.eval_sh_colors(g.means, g.sh, campos, 1, profile=prof)["colors"]
    tol = tl.lookup("sh", "colors", dtype)
    assert np.all(np.abs(got - exp) <= tol.atol + tol.rtol * np.abs(exp))
    plain = refgs.eval_sh_colors(g.means, g.sh, campos, 1)["colors"]
    assert np.abs(got - plain).max() > 1e-3           # and not the reference's convention


@needs_taichi
def test_taichi_projection_stage_is_refgs_without_the_frustum_clamp_float32():
    """project_to_image in float32 equals refgs with no_frustum_clamp + radius_3sigma for
    Gaussians in view (means2d, conics, depths, radii, visible), judged by the oracle's stage
    evaluator."""
    from oracle.adapters.taichi_splatting_backend import taichi_float32 as be

    case = tiny_case("float32", n=5, seed=2).with_config(deviations=TAICHI_PROJECTION)
    v = ev.stage(context(be), case, "projection")
    assert v.ok, v.message()
    assert {"means2d", "conics", "depths", "radii", "visible"} <= v.provided


# ---- the matrix (oracle/matrix.py) --------------------------------------------------------------


def test_matrix_tabulates_columns_and_marks_a_backend_that_cannot_load(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        [sys.executable, "-m", "oracle", "matrix", "--backend", "oracle.adapters.refgs_backend:refgs_float32",
         "--backend", "no_such_renderer:backend", "--clause", "CNV-08", "--max-examples", "2",
         "--report", str(tmp_path)], cwd=root, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = json.loads((tmp_path / "matrix.json").read_text())
    assert [c["spec"] for c in m["columns"]] == ["oracle.adapters.refgs_backend:refgs_float32",
                                                 "no_such_renderer:backend"]
    assert m["columns"][0]["exit_status"] == 0 and "no_such_renderer" in m["columns"][1]["load_error"]
    assert [c["status"] for c in m["clauses"]["CNV-08"]["cells"]] == ["pass", "unavailable"]
    assert (tmp_path / "refgs_float32" / "report.json").exists()
    assert "| CNV-08 | pass" in (tmp_path / "matrix.md").read_text()


@pytest.mark.skipif(not (HAS_GSWARP and HAS_TAICHI), reason="gswarp or taichi-splatting not installed")
def test_outside_renderers_load_by_their_registry_names():
    """``python -m oracle check --backend gswarp32`` (and taichi32 / taichi64) resolve through
    refgs/backends.py to the adapters' objects."""
    from oracle.protocol import load_backend
    gs, t32, t64 = (load_backend(n) for n in ("gswarp32", "taichi32", "taichi64"))
    assert (gs.name, gs.dtype, gs.has_backward) == ("gswarp", "float32", True)
    assert (t32.dtype, t64.dtype) == ("float32", "float64")
    assert set(t32.stages) == set(t64.stages) == {"projection", "sh"}
