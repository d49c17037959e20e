"""DEV-02: the diagnosis names the deviations a backend was built with (oracle/diagnose.py).

Planted backends are refgs with deviations switched on (oracle/meta/deviant.py).  The default
run diagnoses a few of them on the deviations' witness scenes (a few seconds each); the slow run
diagnoses every single observable deviation and 20 seeded pairs and triples, requires the exact
set in at least 95 % of them and never a deviation that is not there, and runs the command line
with the checks' own scenes.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import refgs
from oracle.diagnose import diagnose, explains
from oracle.meta.deviant import deviant, gsplat_as_inria, observable_names, random_combinations
from oracle.protocol import Case
from refgs.deviations import DEVIATIONS, PROFILE_CHOICES

ROOT = Path(__file__).resolve().parents[1]
#: the share of planted sets whose exact set the diagnosis must recover (the issue's bar)
RECOVERY = 0.95


def _witness_only(backend) -> dict:
    return diagnose(backend, checks=[], verify_set=False)


@pytest.mark.parametrize("names", [("no_dilation",), ("clamp_depth_grad_original",),
                                   ("quat_xyzw", "stop_off")])
def test_dev02_planted_deviations_are_recovered(names):
    r = _witness_only(deviant(*names))
    assert set(r["deviations"]) == set(names), r["search"]["trace"]
    w = r["witnesses"]
    assert w["differing"] and set(w["explained"]) == set(w["differing"])
    assert r["summary"].startswith("behaves like the reference with {")


def test_dev02_gsplat_profile_judged_as_inria_is_the_gsplat_choices():
    """Every observable gsplat choice, and nothing else (two choices cannot be observed)."""
    r = _witness_only(gsplat_as_inria)
    observable = {n for n in PROFILE_CHOICES["gsplat"] if DEVIATIONS[n].observable}
    assert set(r["deviations"]) == observable, r["search"]["trace"]


def test_dev02_the_reference_has_nothing_to_explain():
    r = _witness_only(deviant())
    assert r["deviations"] == [] and r["witnesses"]["differing"] == []
    assert "nothing to explain" in r["summary"]


def test_dev02_explains_predicate():
    """explains(deviations, case, backend_output): the shrinker's signature predicate."""
    g, cam, cfg = DEVIATIONS["no_dilation"].witness.build()
    case = Case(g, cam, cfg, seed=1)
    out = deviant("no_dilation").render(g, cam, cfg)
    assert not explains((), case, out)
    assert explains({"no_dilation"}, case, out)
    assert not explains({"dilation_0.1"}, case, out)
    assert explains((), case, refgs.render(g, cam, cfg))


def test_dev02_checks_are_explained_and_verified():
    """The check path: failing checks found, explained under the set, verified on fresh scenes."""
    r = diagnose(deviant("no_frustum_clamp"), checks=["forward_frustum_clamp", "forward_generic"],
                 examples=2, witnesses=False, shrink_failures=False)
    assert r["failing_checks"] == ["forward_frustum_clamp"]
    assert r["deviations"] == ["no_frustum_clamp"]
    assert r["verification"]["explained"] == ["forward_frustum_clamp"]
    assert r["verification"]["new_failures"] == []
    assert r["summary"].endswith("explains 1 of 1 failing checks, 0 new failures")


def test_dev02_unexplained_failures_are_reported_as_such():
    """A backend whose defect is not in the catalogue: no set is named, the failure stays."""
    from oracle.meta.planted import PLANTED
    r = diagnose(PLANTED["sh_band_sign"][0], checks=["forward_sh"], examples=2, witnesses=False,
                 shrink_failures=False)
    assert r["failing_checks"] == ["forward_sh"]
    assert r["deviations"] == []
    assert [u["check"] for u in r["verification"]["unexplained"]] == ["forward_sh"]
    assert r["summary"].startswith("no set of catalogued deviations explains")


@pytest.mark.slow
def test_dev02_recovery_sweep():
    """Every single observable deviation and 20 seeded pairs and triples."""
    sets = [frozenset({n}) for n in observable_names()] + random_combinations(0, 20)
    exact, wrong = [], []
    for s in sets:
        got = set(_witness_only(deviant(*s))["deviations"])
        exact.append(got == s)
        if got - s:
            wrong.append((sorted(s), sorted(got)))
    assert not wrong, f"named deviations that are not there: {wrong}"
    assert sum(exact) >= RECOVERY * len(sets), f"{sum(exact)} of {len(sets)} recovered exactly"


@pytest.mark.slow
def test_dev02_command_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "oracle", "diagnose", "--backend", "oracle.meta.deviant:four_deviations",
           "--report", str(tmp_path), "--max-examples", "2"]
    rep = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    assert rep.returncode in (0, 1), rep.stderr[-2000:]
    result = json.loads((tmp_path / "diagnosis.json").read_text())
    assert set(result["deviations"]) == {"no_dilation", "no_frustum_clamp", "alpha_skip_off",
                                         "rotation_transposed"}, result["search"]["trace"]
    assert "behaves like the reference with" in rep.stdout
    assert (tmp_path / "diagnosis.txt").read_text().startswith("diagnosis of")
