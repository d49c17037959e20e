"""Verdicts a backend's author can trust (docs/spec/oracle.md ORC-02, ORC-12): a failure blames
only the clauses it is evidence against, declared capabilities are honoured by every case the
oracle draws, and declared known differences are reported as ``known``.

The backends are refgs with a small defect or a narrow set of capabilities, run in this process
(the isolation itself is tests/test_oracle_isolation.py) with a few examples per check.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings

import refgs
from oracle.adapters.refgs_backend import RefgsBackend
from oracle.checks import CHECKS, get_check
from oracle.evaluate import Context
from oracle.known import load_file, validate
from oracle.meta.planted import PLANTED
from oracle.protocol import describe_backend
from oracle.report import summary_text
from oracle.runner import Settings, run
from oracle.strategies import Capabilities

EXAMPLES = 3


def _run(obj, names, **kw):
    be = describe_backend(obj, f"test:{type(obj).__name__}")
    return run(be, Settings(max_examples=kw.pop("examples", EXAMPLES), **kw), checks=[get_check(n) for n in names])


def _by(res):
    return {r.check.name: r for r in res.results}


# ---- blame (ORC-12) --------------------------------------------------------------------------------


def test_orc12_backward_only_failure_spares_the_forward_clauses():
    res = _run(PLANTED["conic_offdiag_doubled"][0], ["hard_05", "backward_background"])
    r = _by(res)
    assert r["hard_05"].status == "fail" and r["backward_background"].status == "fail"
    assert r["hard_05"].clause_status == {"HARD-05": "fail", "CNV-03": "pass"}
    assert r["backward_background"].clause_status == {"RAS-07": "fail", "RAS-06": "pass"}
    assert "backward evidence" in r["hard_05"].blame["spared"]["CNV-03"]
    assert {"CNV-03", "RAS-06"}.isdisjoint(res.failed_clauses), res.failed_clauses


class _WrongMeansGradF32(RefgsBackend):
    """refgs at float32 with every output float32, and dL/dmeans 10 % too large."""

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        g = super().render_backward(out, v_image, v_alpha, v_depth)
        return dataclasses.replace(g, means=np.asarray(g.means) * np.float32(1.1))


def test_orc12_dtype_clause_fails_only_on_a_wrong_dtype():
    r = _by(_run(_WrongMeansGradF32("inria", "float32"), ["forward_dtype", "backward_dtype"]))
    assert r["forward_dtype"].status == "pass"
    b = r["backward_dtype"]
    assert b.status == "fail" and b.clause_status == {"CNV-11": "pass", "API-05": "fail"}, b.clause_status
    assert "dtype" in b.blame["spared"]["CNV-11"]


class _NoShWrongShGrad(RefgsBackend):
    """A backend without SH (degree 0) whose SH gradient is 10 % too large."""

    max_sh_degree = 0

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        g = super().render_backward(out, v_image, v_alpha, v_depth)
        return dataclasses.replace(g, sh=np.asarray(g.sh) * 1.1)


def test_orc12_sh_degree_clause_is_not_blamed_without_sh():
    b = _by(_run(_NoShWrongShGrad("inria", "float64"), ["backward_sh"]))["backward_sh"]
    assert b.status == "fail" and b.failure["scene"]["sh_coeffs"] == 1
    assert b.clause_status["SH-04"] == "fail" and b.clause_status["SH-01"] == "pass", b.clause_status


def test_orc12_background_and_opacity_scale_clauses_need_a_case_that_has_them():
    r = _by(_run(PLANTED["half_pixel_shift"][0], ["forward_background", "forward_opacity_scale"]))
    for name, other in (("forward_background", "RAS-06"), ("forward_opacity_scale", "CNV-07")):
        sc = r[name].failure["scene"]
        assert not any(sc["background"]) and not sc["opacity_scale"], sc      # shrunk away: not the cause
        assert r[name].clause_status == {other: "fail", "API-02": "pass"}, r[name].clause_status


# ---- capabilities (ORC-02) ---------------------------------------------------------------------------


class _Narrow:
    """refgs at float64 that renders only SH degree 0 (K = 1), one focal length, a centred
    principal point, a black background and no opacity_scale -- and says so."""

    profile, dtype = "inria", "float64"
    max_sh_degree = 0
    camera_model = "simple_pinhole"
    supports_principal_point = False
    supports_background = False
    supports_opacity_scale = False

    def render(self, gaussians, camera, config):
        if gaussians.sh.shape[1] > 1 or (config.sh_degree or 0) > 0:
            raise RuntimeError("SH degree 3 unsupported")
        if camera.fx != camera.fy or camera.cx != camera.width / 2 or camera.cy != camera.height / 2:
            raise RuntimeError("only a centred principal point and one focal length")
        if any(config.background) or config.opacity_scale is not None:
            raise RuntimeError("no background, no opacity_scale")
        return refgs.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return refgs.render_backward(out, v_image, v_alpha, v_depth)


def test_orc02_every_case_stays_inside_the_declared_capabilities():
    be = describe_backend(_Narrow(), "test:narrow")
    ctx, caps = Context(be), Capabilities.of(be)
    assert caps == Capabilities("inria", 0, "simple_pinhole", False, False)
    for check in CHECKS:
        if check.unavailable(ctx) is not None or check.kind == "errors":
            continue

        @seed(2)
        @settings(max_examples=3, database=None, deadline=None, suppress_health_check=list(HealthCheck))
        @given(case=check.scenes(ctx))
        def draw(case):
            assert caps.admits(case) is None, (check.name, caps.admits(case))

        draw()


def test_orc02_capabilities_declared_missing_give_n_a_and_the_hard_cases_run():
    hard = [c.name for c in CHECKS if c.kind == "hard"]
    res = _run(_Narrow(), hard + ["forward_background", "backward_background", "forward_intrinsics",
                                  "forward_sh", "forward_opacity_scale", "backward_opacity_scale"],
               examples=1, shrink=False)
    r = _by(res)
    bad = {n: (x.status, (x.failure or {}).get("message", "")[:200]) for n, x in r.items()
           if x.status not in ("pass", "n/a")}
    assert not bad and res.exit_status == 0, bad
    reasons = {n: x.reason for n, x in r.items() if x.status == "n/a"}
    assert set(reasons) == {"hard_05", "hard_10", "forward_background", "backward_background",
                            "forward_intrinsics", "forward_sh", "forward_opacity_scale",
                            "backward_opacity_scale"}, reasons
    assert "principal point" in reasons["hard_05"] and "background" in reasons["hard_10"]
    assert "SH degree 0" in reasons["forward_sh"] and "simple_pinhole" in reasons["forward_intrinsics"]


# ---- known differences (ORC-02) ------------------------------------------------------------------------


class _Declared:
    """Wraps a backend object and declares ``known_differences``."""

    def __init__(self, inner, known):
        self._inner, self.known_differences = inner, known
        for k in ("profile", "dtype", "max_sh_degree", "name", "version"):
            setattr(self, k, getattr(inner, k))

    def render(self, *args):
        return self._inner.render(*args)


KNOWN = [{"check": "forward_pixel_centres", "clause": "CNV-08",
          "reason": "we sample pixel corners, as our training data does", "link": "https://example.org/1"}]


def test_orc02_a_declared_known_difference_is_reported_as_known():
    res = _run(_Declared(PLANTED["half_pixel_shift"][0], KNOWN), ["forward_pixel_centres"])
    (r,) = res.results
    assert r.status == "known" and r.clause_status["CNV-08"] == "known" and r.known == KNOWN
    assert res.exit_status == 0 and res.failed_clauses == []
    assert "KNOWN DIFFERENCES" in summary_text(res) and "pixel corners" in summary_text(res)


def test_orc02_a_known_difference_that_stops_happening_fails_the_run():
    res = _run(_Declared(RefgsBackend("inria", "float64"), KNOWN), ["forward_pixel_centres"])
    (r,) = res.results
    assert r.status == "fail" and "no longer happens" in r.failure["message"]
    assert res.exit_status == 1 and res.failed_clauses == ["CNV-08"]


def test_orc02_known_differences_file_and_validation(tmp_path):
    p = tmp_path / "known.toml"
    p.write_text('[[difference]]\ncheck = "forward_coverage"\nclause = "PRF-04"\nreason = "3-sigma radius"\n')
    entries = load_file(p)
    assert entries == ({"check": "forward_coverage", "clause": "PRF-04", "reason": "3-sigma radius"},)
    validate(entries, CHECKS)
    with pytest.raises(ValueError, match="no check is named"):
        validate([{"check": "forward_nothing", "reason": "x"}], CHECKS)
    with pytest.raises(ValueError, match="not RAS-05"):
        validate([{"check": "forward_coverage", "clause": "RAS-05", "reason": "x"}], CHECKS)
    p.write_text('[[difference]]\nclause = "PRF-04"\n')
    with pytest.raises(ValueError, match="known.toml"):
        load_file(p)
