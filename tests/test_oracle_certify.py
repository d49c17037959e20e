"""Every shipped adapter that is installed, certified through the oracle's command line (ORC-08).

This is issue 5's acceptance run inside the default suite: ``python -m oracle check --backend
<adapter>`` in a subprocess, exactly as a backend author runs it, with a small example count.
refgs (both dtypes, both profiles), the torch transcription and the numba backend must pass every
clause (exit status 0).  gsplat's pure-torch CPU functions are expected to fail exactly the two
stage checks whose differences docs/agreement.md documents (its ``F.normalize`` epsilon on
near-degenerate quaternions, its pure-torch radius rule) and nothing else; its render-level
checks are "n/a" without CUDA.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = "4"

#: (adapter, optional module it needs, whether it provides every optional interface: the numba
#: backend offers render and render_backward but no per-stage functions -> "not provided")
PASSING = [(f"{module}:{prefix}{profile}{dtype}", needs, full)
           for module, prefix, needs, full in (
               ("oracle.adapters.refgs_backend", "refgs_", None, True),
               ("oracle.adapters.torch_backend", "torch_", "torch", True),
               ("refgs.fast", "fast_", "numba", False))
           for profile in ("", "gsplat_") for dtype in ("float32", "float64")] + [
    ("refgs.fast:fast_float32_geom64", "numba", False)]    # mixed precision, float32 tolerances

#: gsplat 1.5.3 pure-torch vs refgs: the documented differences (docs/agreement.md)
GSPLAT_KNOWN_FAILURES = {"stage_covariance", "stage_projection"}


def _check(backend: str, report: Path) -> tuple[int, dict, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    res = subprocess.run([sys.executable, "-m", "oracle", "check", "--backend", backend,
                          "--max-examples", EXAMPLES, "--seed", "0", "--report", str(report),
                          "--quiet", "--no-shrink"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    data = json.loads((report / "report.json").read_text())
    return res.returncode, data, res.stdout + res.stderr


def _needs(module: str | None):
    if module is not None and importlib.util.find_spec(module) is None:
        pytest.skip(f"optional extra not installed: {module}")


@pytest.mark.parametrize("backend,module,full", PASSING, ids=[b.split(":")[1] for b, _, _ in PASSING])
def test_shipped_adapter_is_certified(backend, module, full, tmp_path):
    _needs(module)
    rc, data, out = _check(backend, tmp_path)
    failed = [c["name"] for c in data["checks"] if c["status"] == "fail"]
    assert rc == 0 and data["exit_status"] == 0 and not failed, (failed, out[-2000:])
    statuses = {c["status"] for c in data["checks"]}
    allowed = {"pass", "n/a"} if full else {"pass", "n/a", "not provided"}
    assert "pass" in statuses and statuses <= allowed, statuses


def test_gsplat_cpu_adapter_fails_only_where_documented(tmp_path):
    _needs("gsplat")
    rc, data, out = _check("oracle.adapters.gsplat_backend:gsplat_backend", tmp_path)
    by_status: dict[str, set[str]] = {}
    for c in data["checks"]:
        by_status.setdefault(c["status"], set()).add(c["name"])
    assert rc == 1 and data["exit_status"] == 1, out[-2000:]
    assert by_status.get("fail", set()) == GSPLAT_KNOWN_FAILURES, by_status.get("fail")
    assert "stage_sh" in by_status.get("pass", set())
    render_level = [c for c in data["checks"] if c["kind"] in ("forward", "backward")]
    assert render_level and all(c["status"] == "n/a" and "CUDA" in c["reason"] for c in render_level
                                if c["name"] not in GSPLAT_KNOWN_FAILURES)
