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

from oracle.checks import CHECKS
from oracle.protocol import describe_backend, load_backend
from oracle.meta.planted import PLANTED
from oracle.runner import Settings, run

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
    assert sc["width"] * sc["height"] <= 16, sc
    assert r.failure["parameters"], "a one-Gaussian scene lists its parameters"
    cmd = r.failure["replay"].split()
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    rep = subprocess.run([sys.executable, *cmd[1:]], cwd=ROOT, capture_output=True, text=True, env=env)
    assert rep.returncode == 1 and "CNV-08" in rep.stdout, rep.stdout + rep.stderr
