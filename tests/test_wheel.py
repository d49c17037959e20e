"""The wheel, installed outside this repository, works on its own.

The wheel is built from this checkout (``pip wheel``, no build isolation: the installed
setuptools), installed with ``pip install --no-deps --target`` into a temporary folder, and run
from another temporary folder with only that folder on PYTHONPATH (the dependencies come from the
running environment, the checkout's refgs and oracle are shadowed).  It must carry the spec's
clauses (the oracle reads their titles, oracle/clauses.py), run ``python -m oracle check`` and
``refgs demo`` through its console script.  The default run checks the console script with
``refgs demo --help``; the demo itself is marked slow: 2 iterations on the reference backend (the
scene, both trainings, the evaluation with LPIPS, the figure: about a minute on 2 cores, which
.ci/run runs after the test suite) and the full ``refgs demo`` (1000 iterations each, about 90 s
with numba).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "--disable-pip-version-check", "-q", "-w", str(tmp / "dist"), str(ROOT)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    (wheel,) = (tmp / "dist").glob("refgs-*.whl")
    site = tmp / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile",
                        "--disable-pip-version-check", "-q", "--target", str(site), str(wheel)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    work = tmp / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(site)
    return {"site": site, "work": work, "env": env, "wheel": wheel}


def run(installed, *cmd, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], cwd=installed["work"], env=installed["env"],
                          capture_output=True, text=True, timeout=timeout)


def test_the_wheel_is_imported_and_carries_the_spec(installed):
    r = run(installed, sys.executable, "-c",
            "import refgs, oracle; from oracle.clauses import load_clauses; "
            "print(refgs.__file__); print(oracle.__file__); print(len(load_clauses()))")
    assert r.returncode == 0, r.stderr
    refgs_file, oracle_file, n = r.stdout.split()
    site = str(installed["site"])
    assert refgs_file.startswith(site) and oracle_file.startswith(site), r.stdout
    from oracle.clauses import load_clauses
    assert int(n) == len(load_clauses()) > 100


def test_oracle_check_runs_from_the_wheel(installed):
    report = installed["work"] / "report"
    r = run(installed, sys.executable, "-m", "oracle", "check", "--backend",
            "oracle.adapters.refgs_backend:refgs_float32", "--clause", "CNV-08", "--max-examples",
            "2", "--report", report, "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    text = (report / "report.txt").read_text()
    assert "CNV-08" in text and (report / "index.html").is_file()
    assert "not declared" not in r.stdout


def demo(installed, *args):
    out = installed["work"] / "demo"
    r = run(installed, installed["site"] / "bin" / "refgs", "demo", "--out", out, "--quiet", *args)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert (out / "comparison.png").is_file()
    for method in ("3dgs", "fm"):
        metrics = json.loads((out / method / "metrics.json").read_text())
        assert metrics["psnr"] > 5, metrics
    return r


def test_console_script_runs_from_the_wheel(installed):
    r = run(installed, installed["site"] / "bin" / "refgs", "demo", "--help")
    assert r.returncode == 0 and "--backend" in r.stdout, r.stdout + r.stderr


@pytest.mark.slow
def test_refgs_demo_runs_from_the_wheel_briefly(installed):
    demo(installed, "--iters", "2", "--backend", "reference")


@pytest.mark.slow
def test_refgs_demo_runs_from_the_wheel(installed):
    r = demo(installed)
    assert "backend fast" in r.stdout or "backend reference" in r.stdout, r.stdout
