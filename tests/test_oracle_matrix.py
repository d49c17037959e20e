"""The conformance matrix and the diagnosis of a check run (oracle/matrix.py, oracle/triage.py;
docs/conformance.md, docs/spec/deviations.md DEV-02).

* every column's report folder is what ``check`` writes (report.json, report.txt, index.html,
  diagnosis.json), and matrix.html links each cell to that column's page at the clause's row;
* a GPU column on a machine without one says "n/a: no GPU here", an unloadable one
  "unavailable"; the default columns include the CUDA renderers of gsplat and gswarp;
* ``check --diagnose`` writes diagnosis.json, and index.html and report.txt show its line;
* the outside renderers have registry names (refgs/backends.py).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from oracle.matrix import (DEFAULT_COLUMNS, NO_GPU, Column, build_matrix, matrix_html,
                           matrix_markdown)
from oracle.runner import Settings
from refgs.backends import BACKENDS

ROOT = Path(__file__).resolve().parents[1]


def test_matrix_columns_have_full_reports_and_linked_cells(tmp_path):
    cols = [Column("oracle.adapters.refgs_backend:refgs_float32", "refgs float32"),
            Column("oracle.meta.deviant:two_deviations", "two deviations"),
            Column("oracle.adapters.gswarp_backend:gswarp_cuda", "gswarp CUDA", gpu=True),
            Column("no_such_module_xyz:backend", "missing")]
    m = build_matrix(cols, Settings(max_examples=2, clauses=("PRJ-03",)), tmp_path, gpu=False)
    ref, dev, gpu, missing = m["columns"]
    for rec in (ref, dev):
        folder = tmp_path / rec["report"]
        assert {p.name for p in folder.iterdir()} >= {"report.json", "report.txt", "index.html",
                                                      "diagnosis.json"}
        assert rec["page"] == f"{rec['report']}/index.html"
    assert ref["exit_status"] == 0 and dev["exit_status"] == 1
    assert gpu["not_run"] == NO_GPU and gpu["report"] is None and missing["load_error"]
    row = m["clauses"]["PRJ-03"]["cells"]
    assert row[0]["status"] == "pass" and row[1]["status"] == "fail"
    md = matrix_markdown(m)
    assert "n/a: no GPU here" in md and "| unavailable |" in md
    assert "no_frustum_clamp" in dev["diagnosis"]["deviations"] and not dev["diagnosis"]["unexplained"]
    assert "| deviations (diagnosis) | none needed | " + ", ".join(dev["diagnosis"]["deviations"]) \
        + " | - | - |" in md
    page = matrix_html(m)
    assert 'href="two_deviations/index.html#clause-PRJ-03"' in page
    assert 'id="clause-PRJ-03"' in (tmp_path / "two_deviations" / "index.html").read_text()


def test_default_columns_include_the_gpu_renderers():
    gpu = {c.spec.rsplit(":", 1)[1] for c in DEFAULT_COLUMNS if c.gpu}
    assert {"gsplat_cuda", "gswarp_cuda"} <= gpu
    cpu = {c.spec.rsplit(":", 1)[1] for c in DEFAULT_COLUMNS if not c.gpu}
    assert {"refgs_float32", "fast_float32", "fast_float64", "fast_gsplat_float32",
            "fast_float32_geom64", "torch_float32", "gsplat_cpu", "gswarp_cpu", "taichi_float32",
            "taichi_float64"} <= cpu


def test_check_diagnose_writes_the_diagnosis_and_shows_it(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rep = tmp_path / "rep"
    r = subprocess.run([sys.executable, "-m", "oracle", "check", "--backend",
                        "oracle.meta.deviant:two_deviations", "--clause", "PRJ-03",
                        "--max-examples", "2", "--diagnose", "--report", str(rep), "--quiet"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 1, r.stderr[-2000:]
    dg = json.loads((rep / "diagnosis.json").read_text())
    assert dg["available"] and "no_frustum_clamp" in dg["deviations"] and not dg["unexplained"]
    line = dg["summary"]
    assert line.startswith("behaves like the reference with {no frustum clamp in the Jacobian")
    assert line.endswith("0 new failures")
    assert line in (rep / "index.html").read_text() and line in (rep / "report.txt").read_text()
    report = json.loads((rep / "report.json").read_text())
    assert report["diagnosis"]["summary"] == dg["summary"]
    sigs = {c["name"]: c["failure"]["signature"]["deviations"] for c in report["checks"]
            if c["status"] == "fail"}
    assert sigs["forward_frustum_clamp"] == sigs["backward_frustum_clamp"] == ["no_frustum_clamp"]


def test_outside_renderers_have_registry_names():
    """gswarp32, taichi32, taichi64: lazily imported module:object strings with their extra."""
    want = {"gswarp32": ("gswarp_backend:gswarp_float32", "gswarp", "float32"),
            "taichi32": ("taichi_splatting_backend:taichi_float32", "taichi", "float32"),
            "taichi64": ("taichi_splatting_backend:taichi_float64", "taichi", "float64")}
    for name, (target, extra, dtype) in want.items():
        e = BACKENDS[name]
        assert e.target == f"oracle.adapters.{target}" and not e.factory
        assert (e.extra, e.dtype, e.profile) == (extra, dtype, "inria")


def test_conformance_page_shows_the_committed_matrix():
    """docs/conformance.md's table is docs/conformance/matrix.md's, and every column's page the
    matrix links to is there."""
    page = (ROOT / "docs" / "conformance.md").read_text()
    table = page.split("<!-- matrix:begin -->\n", 1)[1].split("<!-- matrix:end -->", 1)[0]
    committed = (ROOT / "docs" / "conformance" / "matrix.md").read_text()
    assert committed.startswith(table) and table.count("\n") > 50
    m = json.loads((ROOT / "docs" / "conformance" / "matrix.json").read_text())
    for col in m["columns"]:
        assert col["not_run"] == NO_GPU or (ROOT / "docs" / "conformance" / col["page"]).is_file()
