"""The oracle's pytest plugin (oracle/pytest_plugin.py) as a backend author runs it: pytest started
in a temporary folder outside this repository, with the plugin loaded from the installed refgs
(entry point ``pytest11``), JUnit XML and the HTML report written, the backend in a worker.

A planted bug (oracle/meta/planted.py) must fail with its clause id in the failing item's name;
refgs.fast's float32 backend must pass.  Without ``--oracle-backend`` the plugin must cost
nothing: the project's own suite loads it too.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import entry_points
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: examples per check: the verdicts of these backends need few (tests/test_oracle_meta.py runs
#: 4); one keeps the faithful backend's 49 checks near 20 s on 2 cores
EXAMPLES = "1"


def author_pytest(folder: Path, *args, timeout: int = 600) -> subprocess.CompletedProcess:
    """``python -m pytest ARGS`` in ``folder`` (outside the repository), as an author's CI runs
    it: no PYTHONPATH, this repository's conftest and pyproject out of sight."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTEST_ADDOPTS")}
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
                          cwd=folder, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def outside(tmp_path) -> Path:
    folder = tmp_path / "author-repo"
    folder.mkdir()
    assert ROOT not in folder.resolve().parents
    return folder


def junit_cases(xml: Path) -> dict:
    """name -> (outcome, {property: value}) of a JUnit XML file."""
    out = {}
    for case in ET.parse(xml).getroot().iter("testcase"):
        outcome = next((c.tag for c in case if c.tag in ("failure", "error", "skipped")), "passed")
        props = {p.get("name"): p.get("value") for p in case.iter("property")}
        out[f"{case.get('classname')}::{case.get('name')}"] = (outcome, props)
    return out


def test_the_plugin_is_an_installed_entry_point():
    (ep,) = [e for e in entry_points(group="pytest11") if e.name == "oracle"]
    assert ep.value == "oracle.pytest_plugin"


def test_planted_bug_fails_with_its_clause_in_the_item_name(outside):
    r = author_pytest(outside, "--oracle-backend", "oracle.meta.planted:half_pixel_shift",
                      "--oracle-clause", "CNV-08", "--oracle-max-examples", "3",
                      "--oracle-no-shrink", "--junitxml", "reports/oracle.xml", "-q")
    assert r.returncode == 1, r.stdout[-3000:] + r.stderr[-3000:]
    cases = junit_cases(outside / "reports" / "oracle.xml")
    failing = {name for name, (outcome, _) in cases.items() if outcome == "failure"}
    assert "oracle::forward_pixel_centres[CNV-08]" in failing, cases
    assert all("CNV-08" in name for name in cases)          # --oracle-clause selected by clause
    outcome, props = cases["oracle::forward_pixel_centres[CNV-08]"]
    assert props["status"] == "fail" and props["clauses"] == "CNV-08"
    report = outside / "reports" / "oracle-report"            # beside the JUnit XML
    assert (report / "index.html").is_file() and (report / "report.txt").is_file()
    data = json.loads((report / "report.json").read_text())
    assert data["backend"]["spec"] == "oracle.meta.planted:half_pixel_shift"
    assert (outside / props["reproducer"]).is_file()
    assert "replay: python -m oracle replay" in r.stdout       # the failure block of the report
    assert "CNV-08" in r.stdout


def test_faithful_backend_passes(outside):
    pytest.importorskip("numba", reason="refgs.fast needs numba (pip install 'refgs[numba]')")
    r = author_pytest(outside, "--oracle-backend", "refgs.fast:fast_float32",
                      "--oracle-max-examples", EXAMPLES, "--junitxml", "junit.xml", "-q")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    cases = junit_cases(outside / "junit.xml")
    from oracle.checks import CHECKS
    assert len(cases) == len(CHECKS)                           # one item per check
    assert {outcome for outcome, _ in cases.values()} <= {"passed", "skipped"}
    assert sum(outcome == "passed" for outcome, _ in cases.values()) > len(CHECKS) // 2
    data = json.loads((outside / "oracle-report" / "report.json").read_text())
    assert data["exit_status"] == 0 and len(data["checks"]) == len(CHECKS)
    assert (outside / "oracle-report" / "index.html").is_file()


#: An author's renderer that declares the inria profile and renders the profile each config asks
#: for (``follows``), and one that renders inria whatever it is asked (``fixed``).
TWO_PROFILE_BACKENDS = """
import dataclasses
import refgs
from refgs.backends import ReferenceBackend


class Follows(ReferenceBackend):
    def __init__(self, follow):
        super().__init__(profile=None, dtype="float64")
        self.profile, self.follow = "inria", follow

    def render(self, gaussians, camera, config):
        if not self.follow:
            config = dataclasses.replace(config, profile="inria")
        return refgs.render(gaussians, camera, config)


follows, fixed = Follows(True), Follows(False)
"""


@pytest.mark.parametrize("name, status", [("follows", 0), ("fixed", 1)])
def test_profile_option_judges_the_backend_in_that_profile(outside, name, status):
    (outside / "two_profiles.py").write_text(TWO_PROFILE_BACKENDS)
    r = author_pytest(outside, "--oracle-backend", f"two_profiles:{name}", "--oracle-profile",
                      "gsplat", "--oracle-clause", "PRF-03", "--oracle-max-examples", "2",
                      "--oracle-no-shrink", "-q")
    assert r.returncode == status, r.stdout[-3000:] + r.stderr[-3000:]
    data = json.loads((outside / "oracle-report" / "report.json").read_text())
    assert data["backend"]["profile"] == "gsplat"


def test_a_backend_that_cannot_load_stops_the_session_with_status_2(outside):
    r = author_pytest(outside, "--oracle-backend", "no_such_module:backend", "-q",
                      "--oracle-clause", "CNV-08")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "oracle: error:" in r.stdout + r.stderr and "no_such_module" in r.stdout + r.stderr


def test_collect_only_lists_one_item_per_check_with_clause_ids(outside):
    r = author_pytest(outside, "--oracle-backend", "any_module:never_loaded", "--collect-only",
                      "-q")
    assert r.returncode == 0, r.stdout + r.stderr
    from oracle.checks import CHECKS
    items = [ln for ln in r.stdout.splitlines() if ln.startswith("oracle::")]
    assert len(items) == len(CHECKS)
    assert "oracle::forward_pixel_centres[CNV-08]" in items


def test_without_the_option_the_plugin_imports_nothing_and_adds_nothing(outside):
    (outside / "test_probe.py").write_text(
        "import sys\n"
        "def test_probe():\n"
        "    assert 'oracle.pytest_plugin' in sys.modules\n"
        "    heavy = sorted(m for m in ('refgs', 'oracle.checks', 'oracle.runner', 'oracle.isolation')\n"
        "                   if m in sys.modules)\n"
        "    assert heavy == [], heavy\n")
    r = author_pytest(outside, "-q")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 passed" in r.stdout and "oracle::" not in r.stdout
