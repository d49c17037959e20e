"""Meta-tests of the oracle (ORC-10): it passes refgs and fails every planted bug with its clause.

Each planted backend (oracle/meta/planted.py) is refgs with one defect.  The oracle is run on the
checks that cite the defect's clause and must fail that clause; for the backward-only defects
every forward check must still pass (the defect is invisible in the images).  refgs itself, at
float64 and float32 and in both profiles, must pass every check.  Small example counts and a
fixed seed keep this inside the test budget.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import numpy as np

import refgs
from oracle import blame
from oracle.checks import CHECKS, get_check
from oracle.evaluate import Context
from oracle.protocol import Case, describe_backend, load_backend
from oracle.meta import planted
from oracle.meta.planted import PLANTED
from oracle.runner import Settings, run
from oracle.shrink import shrink
from oracle.strategies import unproject

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = 4


@pytest.mark.parametrize("spec", ["refgs_float64", "refgs_float32", "refgs_gsplat_float32"])
def test_orc10_refgs_passes_every_check(spec):
    be = load_backend(f"oracle.adapters.refgs_backend:{spec}")
    res = run(be, Settings(max_examples=EXAMPLES, shrink=False))
    bad = {r.check.name: r.failure["message"][:300] for r in res.results if r.status == "fail"}
    assert res.exit_status == 0 and not bad, bad
    statuses = {r.status for r in res.results}
    assert statuses <= {"pass", "n/a"}, statuses       # refgs provides every optional interface


@pytest.mark.parametrize("name", sorted(PLANTED))
def test_orc10_planted_bug_fails_with_its_clause(name):
    backend, clause, backward_only = PLANTED[name]
    be = describe_backend(backend, f"oracle.meta.planted:{name}")
    checks = [c for c in CHECKS if clause in c.clauses]
    if backward_only:
        checks += [c for c in CHECKS if c.kind == "forward" and c not in checks]
    res = run(be, Settings(max_examples=EXAMPLES, shrink=False), checks=checks)
    assert clause in res.failed_clauses, (name, res.failed_clauses)
    if backward_only:
        fwd = {r.check.name: r.failure["message"][:200] for r in res.results
               if r.check.kind == "forward" and r.status == "fail"}
        assert not fwd, f"{name} is backward-only, but forward checks failed: {fwd}"


def test_orc06_failure_is_shrunk_to_a_small_replayable_scene(tmp_path):
    be = describe_backend(PLANTED["half_pixel_shift"][0], "oracle.meta.planted:half_pixel_shift")
    checks = [c for c in CHECKS if c.name == "forward_pixel_centres"]
    res = run(be, Settings(max_examples=EXAMPLES, shrink=True, report_dir=str(tmp_path)), checks=checks)
    (r,) = res.results
    assert r.status == "fail"
    sc = r.failure["scene"]
    assert sc["n_gaussians"] == 1, sc
    # cropping stops where the frustum-clamp limits would reach the Gaussian (its mechanism)
    (w0, h0), (w1, h1) = r.failure["shrink"]["image"]
    assert w1 * h1 <= 64 and w1 * h1 < w0 * h0, r.failure["shrink"]
    assert r.failure["parameters"], "a one-Gaussian scene lists its parameters"
    cmd = r.failure["replay"].split()
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    rep = subprocess.run([sys.executable, *cmd[1:]], cwd=ROOT, capture_output=True, text=True, env=env)
    assert rep.returncode == 1 and "CNV-08" in rep.stdout, rep.stdout + rep.stderr


def _two_defect_case(u: float, log_scale: float) -> Case:
    """One round Gaussian at image column ``u`` (pixels) of a 48 x 32 inria camera."""
    cam = refgs.Camera.look_at([0.0, 0.0, -4.0], [0, 0, 0], fx=40.0, width=48, height=32)
    g = refgs.Gaussians(unproject(cam, np.array([u]), np.array([16.0]), np.array([4.0])),
                        np.full((1, 3), log_scale), np.array([[1.0, 0, 0, 0]]), np.array([2.0]),
                        np.full((1, 1, 3), 0.2))
    return Case(g, cam, refgs.RenderConfig(profile="inria", sh_degree=0), seed=3, label="two defects")


def test_orc06_shrinking_keeps_the_defect_of_the_failure():
    """Two planted defects in dL/dmeans, one under the frustum clamp and one outside it: each
    failing case shrinks to a case that still shows its own defect.  Without the mechanism rule
    the unclamped Gaussian's case is cropped until the Gaussian is clamped, and shows the other."""
    check = get_check("backward_frustum_clamp")
    ctx = {name: Context(describe_backend(getattr(planted, name), f"oracle.meta.planted:{name}"))
           for name in ("two_defects", "clamp_defect_only", "unclamped_defect_only")}

    def evaluate(s):
        return check.evaluate(ctx["two_defects"], s)

    def mechanism(s, v):
        return blame.mechanism(v, blame.facts(s))

    def shows(s):
        return {n: not check.evaluate(ctx[n], s).ok for n in ("clamp_defect_only", "unclamped_defect_only")}

    for case, own in ((_two_defect_case(43.0, -2.0), "unclamped_defect_only"),   # inside the limits
                      (_two_defect_case(62.0, -0.6), "clamp_defect_only")):      # beyond them, tail in
        assert shows(case) == {n: n == own for n in ("clamp_defect_only", "unclamped_defect_only")}
        v = evaluate(case)
        small, _, stats = shrink(evaluate, case, v, mechanism=mechanism)
        assert stats.size_after[0] * stats.size_after[1] < 48 * 32
        assert shows(small) == {n: n == own for n in ("clamp_defect_only", "unclamped_defect_only")}, (
            own, stats.to_json())
        if own == "unclamped_defect_only":
            switched, _, _ = shrink(evaluate, case, v)          # the old rule: any failure of dmeans
            assert shows(switched) == {"clamp_defect_only": True, "unclamped_defect_only": False}
            assert stats.rejected > 0


def test_orc06_crops_keep_a_centred_principal_point_when_the_backend_needs_one():
    case = _two_defect_case(30.0, -2.0)
    assert blame.facts(case).visible.all()

    def evaluate(s):                       # a stand-in check: fails while the Gaussian is visible
        from oracle.compare import fine, problem
        from oracle.evaluate import Verdict
        vis = bool(blame.facts(s).visible.any())
        return Verdict([problem("image", "visible", "value") if vis else fine("image")])

    small, _, stats = shrink(evaluate, case, evaluate(case), centred=True)
    c = small.camera
    assert (c.width, c.height) != (48, 32), stats.to_json()
    assert (c.cx, c.cy) == (c.width / 2, c.height / 2), (c.cx, c.cy, c.width, c.height)
