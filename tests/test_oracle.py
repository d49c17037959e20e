"""The oracle's own machinery: clauses, tolerance table, comparison helpers, near-ties, strategies,
hard cases, reports, reproducers and the command line (docs/spec/oracle.md ORC-01..ORC-09).

With ``REFGS_ORACLE_BACKEND=module:object`` set, ``test_backend_conformance`` also runs every
check against that backend as one parametrised pytest test per check (skipped otherwise):

    REFGS_ORACLE_BACKEND=oracle.adapters.refgs_backend:refgs_float32 \\
        python -m pytest tests/test_oracle.py -k conformance
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings

import refgs
from oracle import tolerances as tl
from oracle.checks import CHECKS, cited_clauses, get_check
from oracle.clauses import RENDERER_PREFIXES, expand_selection, load_clauses, renderer_clauses
from oracle.compare import compare_exact, compare_gradient, compare_values
from oracle.evaluate import Context
from oracle.hard_cases import HARD_CASES
from oracle.protocol import BackendError, Case, describe_backend, load_backend, raw_gradients, to_activated
from oracle.report import SCHEMA, atomic_write_text, load_case, save_case
from oracle.runner import Settings, run, run_check
from oracle.strategies import MAX_GAUSSIANS, MAX_HEIGHT, MAX_WIDTH, Capabilities
from oracle.ties import tie_distances

ROOT = Path(__file__).resolve().parents[1]
F64 = "oracle.adapters.refgs_backend:refgs_float64"
ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _cli(*args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "oracle", *args], cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def _scene(n=3, seed_=0, profile="inria", **cfg):
    rng = np.random.default_rng(seed_)
    cam = refgs.Camera.look_at([0.3, -0.2, -4.0], [0, 0, 0], fx=50.0, width=40, height=30)
    g = refgs.Gaussians(rng.normal(0, 0.5, (n, 3)), rng.uniform(-2.5, -1.5, (n, 3)),
                        rng.normal(size=(n, 4)), rng.uniform(0, 3, n), rng.normal(0, 0.5, (n, 16, 3)))
    return Case(g, cam, refgs.RenderConfig(profile=profile, **cfg), seed=seed_, label="test")


# ---- clauses (ORC-09) ---------------------------------------------------------------------------


def test_orc09_clause_headings_are_parsed(tmp_path):
    (tmp_path / "a.md").write_text("# T\n#### ABC-01: First rule\ntext\n#### ABC-02:   Second  \n"
                                   "### XYZ-03: not a clause (level 3)\n#### abc-04: lower case\n")
    cl = load_clauses(tmp_path)
    assert list(cl) == ["ABC-01", "ABC-02"]
    assert cl["ABC-02"].title == "Second" and cl["ABC-01"].line == 2 and cl["ABC-01"].file == "a.md"
    (tmp_path / "b.md").write_text("#### ABC-01: again\n")
    with pytest.raises(ValueError, match="ABC-01 already declared"):
        load_clauses(tmp_path)


def test_orc09_every_renderer_clause_has_a_check_and_every_citation_exists():
    """Meta-test: a renderer clause (CNV, COV, PRJ, SH, RAS, PRF, API, HARD) without a check, or a
    check citing a clause the spec does not declare, fails here."""
    declared = load_clauses()
    assert declared, "docs/spec/*.md declares no clauses"
    cited = cited_clauses()
    unchecked = [c for c in renderer_clauses(declared) if c not in cited]
    unknown = sorted(c for c in cited if c not in declared)
    assert not unchecked, f"renderer clauses with no oracle check: {unchecked}"
    assert not unknown, f"checks cite clauses docs/spec does not declare: {unknown}"
    assert {p for p in RENDERER_PREFIXES} <= {c.split("-")[0] for c in declared}


def test_orc09_reference_only_checks_are_labelled():
    ref_only = [c for c in CHECKS if c.kind == "reference"]
    assert [c.name for c in ref_only] == ["reference_chunking"]
    assert ref_only[0].clauses == ("RAS-09",) and "reference-only" in ref_only[0].doc


def test_orc08_clause_selection():
    known = cited_clauses()
    assert expand_selection(["ras-05", "CNV-08,HARD-07"], known) == {"RAS-05", "CNV-08", "HARD-07"}
    assert expand_selection(["PRF"], known) == {f"PRF-0{i}" for i in range(1, 9)}
    with pytest.raises(ValueError, match="ZZZ-01"):
        expand_selection(["ZZZ-01"], known)


# ---- tolerance table (ORC-03) -----------------------------------------------------------------------


def test_orc03_every_row_has_a_rationale_and_gradient_rows_have_whole_tensor_limits():
    for (stage, output, dtype), t in tl.TABLE.items():
        assert t.rationale.strip(), (stage, output, dtype)
        assert dtype in ("float32", "float64")
        if stage == "backward":
            assert isinstance(t, tl.GradTol) and t.scaled
            assert 0 < t.max_rel_l2 < 1 and 0 < t.min_cosine < 1 and 0 < t.min_mag_ratio < 1
        if t.exact:
            assert t.rtol == 0 and t.atol == 0
        if dtype == "float32" and not t.exact:
            assert t.measured is not None and t.measured_by, (stage, output)
    for dt in ("float32", "float64"):
        for out in ("image", "alpha", "depth", "means2d", "depths", "conics", "colors", "opacities",
                    "radii", "n_contrib", "visible"):
            tl.lookup("render", out, dt)
        for f in ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d"):
            tl.lookup("backward", f, dt)
        assert tl.TIE_BANDS[dt].rationale
    with pytest.raises(KeyError, match="no row"):
        tl.lookup("render", "image", "float16")


def test_orc03_docs_show_the_table_as_it_is():
    """docs/oracle.md embeds ``python -m oracle tolerances`` verbatim between its markers."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "oracle.md").read_text(encoding="utf-8")
    begin, end = "<!-- tolerance-table:begin -->\n", "<!-- tolerance-table:end -->"
    assert begin in doc and end in doc
    embedded = doc.split(begin, 1)[1].split(end, 1)[0]
    assert embedded == tl.markdown_table(), "regenerate with: python -m oracle tolerances"
    assert embedded.count("\n| ") == len(tl.TABLE) + 1 + len(tl.TIE_BANDS)   # rows, tie header, ties


def test_orc03_float32_rows_are_tighter_than_float32_noise_would_need_and_not_looser_than_planted_bugs():
    """The float32 image row must be far below what the planted half-pixel shift produces."""
    t = tl.lookup("render", "image", "float32")
    assert t.atol < 1e-3 and t.rtol < 1e-3
    g = tl.lookup("backward", "means", "float32")
    assert g.max_rel_l2 <= 1e-2 and g.min_cosine >= 0.999


# ---- comparison helpers -------------------------------------------------------------------------------


def test_compare_values_fails_when_it_should_and_counts_flips():
    tol = tl.Tol(1e-6, 1e-6, "test")
    ref = np.linspace(0, 1, 12).reshape(3, 4)
    assert compare_values("x", ref + 5e-7, ref, tol).ok
    bad = ref.copy()
    bad[1, 2] += 1e-3
    c = compare_values("x", bad, ref, tol)
    assert not c.ok and c.index == (1, 2) and c.n_bad == 1 and "x[1, 2]=" in c.message
    ex = np.zeros((3, 4), bool)
    ex[1, 2] = True
    c = compare_values("x", bad, ref, tol, exempt=ex)
    assert c.ok and c.ties == {"elements_in_band": 1, "flips": 1}
    assert not compare_exact("n", np.array([1, 2, 3]), np.array([1, 2, 4])).ok


def test_compare_gradient_catches_dropped_and_doubled_rows():
    rng = np.random.default_rng(0)
    ref = rng.normal(size=(20, 3))
    tol = tl.lookup("backward", "means", "float32")
    assert compare_gradient("g", ref * (1 + 1e-7), ref, tol).ok
    dropped = ref.copy()
    dropped[7] = 0
    c = compare_gradient("g", dropped, ref, tol)
    assert not c.ok and "magnitude ratio" in c.message
    assert not compare_gradient("g", 2 * ref, ref, tol).ok
    # rounding noise on a tensor that is zero in exact arithmetic passes with a companion size
    noise = rng.normal(size=(5, 4)) * 1e-17
    assert compare_gradient("q", noise, np.zeros((5, 4)), tl.lookup("backward", "quats", "float64"),
                            companion=np.ones(5)).ok


# ---- near-ties (ORC-04) ------------------------------------------------------------------------------------


def _one_gaussian(logit, mean_px=(10.5, 8.5), log_scale=-2.0, profile="inria"):
    cam = refgs.Camera(np.eye(4), np.array([[40.0, 0, 10], [0, 40.0, 8], [0, 0, 1]]), 20, 16)
    z = 4.0
    mean = np.array([(mean_px[0] - 10) / 40 * z, (mean_px[1] - 8) / 40 * z, z])
    g = refgs.Gaussians(mean[None], np.full((1, 3), log_scale), np.array([[1.0, 0, 0, 0]]),
                        np.array([logit]), np.zeros((1, 1, 3)))
    return refgs.render(g, cam, refgs.RenderConfig(profile=profile))


def test_orc04_alpha_at_one_over_255_is_a_near_tie():
    o = 1 / 255 * (1 + 1e-7)                     # centre pixel alpha = o exactly (G = 1)
    out = _one_gaussian(np.log(o / (1 - o)))
    d = tie_distances(out)
    assert d.alpha[8, 10] < 1e-6
    m = d.masks(tl.TIE_BANDS["float32"])
    assert m["forward"][8, 10] and m["counts"]["alpha"] >= 1
    far = tie_distances(_one_gaussian(2.0))
    assert not far.masks(tl.TIE_BANDS["float32"])["forward"].any()


def test_orc04_conditioning_allowance_grows_with_elongation_only():
    """Round Gaussians get an allowance of a few eps; a 1e4:1 needle far more (ORC-04)."""
    cam = refgs.Camera(np.eye(4), np.array([[40.0, 0, 10], [0, 40.0, 8], [0, 0, 1]]), 20, 16)

    def cond(log_scales):
        g = refgs.Gaussians(np.array([[0.0, 0.0, 4.0]]), np.array([log_scales]),
                            np.array([[0.9, 0.1, 0.3, 0.2]]), np.array([2.0]), np.zeros((1, 1, 3)))
        d = tie_distances(refgs.render(g, cam))
        return d.cond[0], d.cond_pixel.max()

    c_round, px_round = cond([-2.0, -2.0, -2.0])
    c_needle, px_needle = cond([0.0, -9.2, -9.2])
    eps32 = float(np.finfo(np.float32).eps)
    assert tl.COND_MARGIN * eps32 * px_round < 1e-5          # far inside the float32 image row
    assert c_needle > 1e3 * c_round and px_needle > 1e3 * px_round


def test_orc04_geometry_decisions_reproduce_the_reference():
    """At zero perturbation the tie module's decisions are refgs' own (visibility, radii)."""
    from oracle.ties import _decisions, _depth_ok, _permissive
    for profile in ("inria", "gsplat"):
        s = _scene(12, 3, profile)
        out = refgs.render(s.gaussians, s.camera, s.config)
        p = refgs.get_profile(profile)
        cov = refgs.covariance_3d(s.gaussians.quats, s.gaussians.log_scales)["cov3d"]
        p2d = refgs.project_gaussians(s.gaussians.means, cov, out.opacities, s.camera, _permissive(p))
        a, b, c = (p2d["cov2d"][:, k] for k in range(3))
        vis, rx, ry, _ = _decisions(p2d["means2d"], a, b, c, out.opacities, _depth_ok(p2d["depths"], p),
                                    s.camera.width, s.camera.height, p, 1.0)
        assert np.array_equal(vis, out.visible)
        assert np.array_equal(rx, out.radii[:, 0]) and np.array_equal(ry, out.radii[:, 1])


def test_orc05_inputs_are_rounded_once_and_shared():
    from oracle.evaluate import cotangents
    s = _scene(6, 4, background=(0.1, 0.7, 0.3), opacity_scale=np.linspace(0.1, 1.2, 6))
    r = s.rounded("float32")
    for f in refgs.Gaussians.FIELDS:
        a = getattr(r.gaussians, f)
        assert a.dtype == np.float64 and np.array_equal(a.astype(np.float32).astype(np.float64), a)
        assert not np.array_equal(a, getattr(s.gaussians, f)) or f == "sh"
    for a in (r.camera.K, r.camera.world_to_camera, np.asarray(r.config.background),
              r.config.opacity_scale):
        a = np.asarray(a, np.float64)
        assert np.array_equal(a.astype(np.float32).astype(np.float64), a)
    again = r.rounded("float32")
    assert all(np.array_equal(getattr(again.gaussians, f), getattr(r.gaussians, f))
               for f in refgs.Gaussians.FIELDS)
    assert s.rounded("float64") is s
    v = cotangents(r, (30, 40), "float32", kinds=("image", "alpha"))
    assert set(v) == {"v_image", "v_alpha"}
    assert np.array_equal(v["v_image"].astype(np.float32).astype(np.float64), v["v_image"])


# ---- protocol helpers (ORC-01, ORC-02) ---------------------------------------------------------------------


def test_orc01_activated_parameter_helpers_round_trip():
    s = _scene(5, 1)
    g = s.gaussians.replace(quats=s.gaussians.quats * np.array([1e-20, 1, 3, 7, 1e5])[:, None])
    out = refgs.render(g, s.camera, s.config)
    ref = refgs.render_backward(out, np.random.default_rng(0).normal(size=out.image.shape))
    act = to_activated(g)
    assert np.allclose(np.linalg.norm(act["quats"], axis=1), 1)
    # activated-parameter gradients of the same loss, expressed through refgs' raw ones
    v_scales = ref.log_scales / act["scales"]
    v_op = ref.opacity_logits / (act["opacities"] * (1 - act["opacities"]))
    q_norm = np.linalg.norm(g.quats, axis=1)[:, None]
    v_u = ref.quats * q_norm                      # (I - u u^T) v_u: the tangential part is enough
    back = raw_gradients(g, ref.means, v_scales, v_u, v_op, ref.sh, ref.means2d)
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d"):
        np.testing.assert_allclose(getattr(back, f), getattr(ref, f), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="Gaussians.quats"):
        to_activated(g.replace(quats=np.zeros((5, 4))))


def test_orc02_backend_loading_and_capabilities():
    be = load_backend(F64)
    assert be.profile == "inria" and be.dtype == "float64" and be.has_backward
    assert set(be.stages) == {"covariance", "projection", "sh", "composite"}
    assert be.backward_kwargs == {"v_alpha", "v_depth"}
    with pytest.raises(BackendError, match="cannot import module"):
        load_backend("no_such_module_xyz:obj")
    with pytest.raises(BackendError, match="no attribute 'nope'"):
        load_backend("oracle.adapters.refgs_backend:nope")

    class Bad:
        profile = "unity"
        dtype = "float32"

        def render(self, g, c, cfg):
            return None
    with pytest.raises(BackendError, match="'profile' must be one of"):
        describe_backend(Bad())

    class ForwardOnly:
        profile, dtype = "gsplat", "float32"

        def render(self, g, c, cfg):
            return {}
    fo = describe_backend(ForwardOnly())
    assert not fo.has_backward and not fo.supports_antialiased and fo.max_sh_degree == 3
    ctx = Context(fo)
    assert get_check("backward_generic").unavailable(ctx)[0] == "not provided"
    assert get_check("forward_antialiased").unavailable(ctx)[0] == "n/a"
    assert get_check("stage_sh").unavailable(ctx)[0] == "not provided"


# ---- strategies and hard cases (ORC-06) ------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
def test_hard_case_builders_make_small_valid_scenes(profile):
    for cid, case in HARD_CASES.items():
        for s in range(3):
            sc = case.build(np.random.default_rng(s), Capabilities(profile))
            assert sc.n <= MAX_GAUSSIANS and sc.camera.width <= MAX_WIDTH and sc.camera.height <= MAX_HEIGHT
            out = refgs.render(sc.gaussians, sc.camera, sc.config)
            assert np.all(np.isfinite(out.image)), cid


def test_strategies_make_small_valid_scenes_for_every_check():
    be = load_backend("oracle.adapters.refgs_backend:refgs_gsplat_float64")
    ctx = Context(be)
    for check in CHECKS:
        if check.unavailable(ctx) or check.kind == "errors":
            continue
        seen = []

        @seed(1)
        @settings(max_examples=3, database=None, deadline=None,
                  suppress_health_check=list(HealthCheck))
        @given(scene=check.scenes(ctx))
        def draw(scene):
            seen.append(scene)
            assert scene.n <= MAX_GAUSSIANS and scene.camera.width <= MAX_WIDTH
            assert scene.camera.height <= MAX_HEIGHT
            refgs.render(scene.gaussians, scene.camera, scene.config)

        draw()
        assert seen, check.name


# ---- reports, reproducers, CLI (ORC-06..ORC-08) ------------------------------------------------------------


def test_orc06_reproducer_round_trip(tmp_path):
    s = _scene(4, 2, "gsplat", background=(0.1, 0.2, 0.3), sh_degree=2,
               opacity_scale=np.array([0.5, 1.0, 1.5, 0.0]))
    p = save_case(tmp_path / "r.npz", s, check="forward_generic", clauses="RAS-06")
    with np.load(p, allow_pickle=False) as z:
        assert "means" in z.files
    back, meta = load_case(p)
    assert meta == {"check": "forward_generic", "clauses": "RAS-06"}
    for f in refgs.Gaussians.FIELDS:
        np.testing.assert_array_equal(getattr(back.gaussians, f), getattr(s.gaussians, f))
    assert back.config.profile == "gsplat" and back.config.sh_degree == 2
    np.testing.assert_array_equal(back.config.opacity_scale, s.config.opacity_scale)
    assert back.camera.width == 40 and back.seed == 2
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        load_case(tmp_path / "bad.npz")


def test_orc07_atomic_write_leaves_no_temporary(tmp_path):
    atomic_write_text(tmp_path / "sub" / "x.txt", "hello")
    assert (tmp_path / "sub" / "x.txt").read_text() == "hello"
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["x.txt"]


def test_orc07_orc08_cli_check_report_and_exit_status(tmp_path):
    r = _cli("check", "--backend", F64, "--clause", "CNV-08,RAS-09", "--max-examples", "2",
             "--report", str(tmp_path / "ok"), "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((tmp_path / "ok" / "report.json").read_text())
    assert rep["schema"] == SCHEMA and rep["exit_status"] == 0
    assert rep["refgs"] == {"version": refgs.__version__, "spec_version": refgs.SPEC_VERSION}
    assert rep["backend"]["spec"] == F64 and rep["backend"]["dtype"] == "float64"
    assert rep["machine"]["cpu_count"] >= 1 and rep["settings"]["seed"] == 0
    assert rep["clauses"]["CNV-08"]["status"] == "pass"
    assert rep["clauses"]["RAS-09"]["reference_only"] is True
    assert (tmp_path / "ok" / "report.txt").read_text().startswith("oracle: backend")

    bad = _cli("check", "--backend", "oracle.meta.planted:half_pixel_shift", "--clause", "CNV-08",
               "--max-examples", "3", "--report", str(tmp_path / "bad"))
    assert bad.returncode == 1, bad.stdout + bad.stderr
    rep = json.loads((tmp_path / "bad" / "report.json").read_text())
    assert rep["clauses"]["CNV-08"]["status"] == "fail"
    fail = next(c for c in rep["checks"] if c["status"] == "fail")["failure"]
    assert Path(fail["reproducer"]).is_file() and "python -m oracle replay" in fail["replay"]
    assert "replay:" in bad.stdout and "smallest scene" in bad.stdout
    # the replay command reproduces the failure, and refgs passes the same scene
    again = _cli(*fail["replay"].split()[3:])
    assert again.returncode == 1 and "result: fail" in again.stdout
    ok = _cli("replay", fail["reproducer"], "--backend", F64)
    assert ok.returncode == 0 and "result: pass" in ok.stdout


def test_orc08_cli_usage_errors_and_list(tmp_path):
    r = _cli("check", "--backend", F64, "--clause", "NOPE-01", "--report", str(tmp_path))
    assert r.returncode == 2 and "NOPE-01" in r.stderr
    r = _cli("check", "--backend", "no_such_mod:x", "--report", str(tmp_path))
    assert r.returncode == 2 and "cannot import" in r.stderr
    r = _cli("list-clauses")
    assert r.returncode == 0 and "RAS-09" in r.stdout and "reference-only" in r.stdout


def test_orc08_backend_module_found_from_the_current_directory(tmp_path):
    (tmp_path / "mybackend.py").write_text(
        "from oracle.adapters.refgs_backend import RefgsBackend\nb = RefgsBackend('inria', 'float64')\n")
    r = _cli("check", "--backend", "mybackend:b", "--clause", "API-03", "--max-examples", "2",
             "--report", str(tmp_path / "rep"), "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr


def test_oracle_imports_without_torch():
    code = ("import sys, oracle.runner, oracle.checks, oracle.__main__, oracle.meta.planted, "
            "oracle.adapters.refgs_backend, oracle.adapters.template; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_template_backend_passes_a_quick_check():
    be = load_backend("oracle.adapters.template:backend")
    res = run(be, Settings(max_examples=2, shrink=False, clauses=("RAS-06", "API-05")))
    assert res.exit_status == 0, [r.failure for r in res.results if r.failure]


def test_check_result_reports_worst_ratio_and_examples():
    r = run_check(Context(load_backend(F64)), get_check("forward_pixel_centres"), Settings(max_examples=2))
    assert r.status == "pass" and r.examples == 2 and r.worst_ratio is not None and r.worst_ratio <= 1


# ---- REFGS_ORACLE_BACKEND: conformance of any backend as pytest tests -----------------------------------

_BACKEND = os.environ.get("REFGS_ORACLE_BACKEND")
_EXAMPLES = int(os.environ.get("REFGS_ORACLE_MAX_EXAMPLES", "20"))


@pytest.mark.skipif(not _BACKEND, reason="set REFGS_ORACLE_BACKEND=module:object to run the oracle")
@pytest.mark.parametrize("check", CHECKS, ids=[f"{c.name}[{c.clauses[0]}]" for c in CHECKS])
def test_backend_conformance(check, tmp_path):
    ctx = Context(load_backend(_BACKEND))
    r = run_check(ctx, check, Settings(max_examples=_EXAMPLES, report_dir=str(tmp_path)))
    if r.status in ("n/a", "not provided"):
        pytest.skip(f"{r.status}: {r.reason}")
    assert r.status == "pass", (f"{check.name} [{', '.join(check.clauses)}]: {r.failure['message']}\n"
                                f"replay: {r.failure.get('replay')}")
