"""The teaching notebooks run headless and their own checks pass.

Each ``docs/notebooks/NN_*.py`` (jupytext percent format) is converted to a notebook with
jupytext and executed with nbclient in a ``python3`` kernel, with ``MPLBACKEND=Agg`` and a
temporary working directory; ``PYTHONPATH`` starts with the repository root (this checkout's
refgs and oracle) and ``docs/notebooks`` (the notebooks' ``_helpers``).  The kernel is pinned to the interpreter running the tests: a
``python3`` kernelspec whose argv starts with ``sys.executable`` is written to a temporary folder
put first on ``JUPYTER_PATH``, so neither a registered ipykernel spec nor a stale one in the user's
Jupyter folders is needed or used.  Kernel connection files and the IPython profile go to the
temporary folder too.  The notebooks hold ``assert`` cells for their key claims (FD errors below
1e-6, the oracle's verdicts, ...); a failing assert fails the test with the cell's traceback.
Each notebook must finish within ``TIME_LIMIT_S`` on 2 cores.

Executing needs the ``notebooks`` extra (jupytext, nbclient, nbformat, ipykernel) and is skipped
without it; the checks of the files' headers and of docs/notebooks/_helpers.py run always.
"""
from __future__ import annotations

import importlib.util
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "docs" / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.py"))
#: The five notebooks of docs/notebooks/README.md.
EXPECTED = ("01_one_gaussian", "02_gradients_by_hand", "03_sap", "04_train_tiny", "05_certify_backend")
#: Wall-clock budget per notebook (docs/notebooks/README.md: "well under two minutes on two
#: cores"), kernel start included.
TIME_LIMIT_S = 120.0
#: nbclient's per-cell timeout: generous, so that a slow cell fails on the time assertion below
#: with its measured time rather than as a kernel timeout.
CELL_TIMEOUT_S = 600
#: The jupytext header every notebook carries (pairing with .ipynb, percent format, kernel).
HEADER_KEYS = ("formats: ipynb,py:percent", "format_name: percent", "name: python3")


def load_helpers():
    """docs/notebooks/_helpers.py as a module (by path: it is not part of the refgs package)."""
    spec = importlib.util.spec_from_file_location("notebook_helpers", NOTEBOOK_DIR / "_helpers.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


helpers = load_helpers()


def test_all_notebooks_present():
    assert tuple(p.stem for p in NOTEBOOKS) == EXPECTED


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_has_jupytext_header(path):
    head = path.read_text(encoding="utf-8").split("# ---", 2)
    assert len(head) == 3 and head[0] == "", f"{path.name}: no jupytext header at the top"
    for key in HEADER_KEYS:
        assert key in head[1], f"{path.name}: jupytext header lacks {key!r}"


def pin_kernel(folder: Path) -> str:
    """Write a ``python3`` kernelspec running this interpreter under ``folder``; return the
    folder to put first on JUPYTER_PATH."""
    spec = folder / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (refgs tests)", "language": "python"}))
    return str(folder)


@pytest.mark.notebook
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch):
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = jupytext.read(path)
    n_asserts = sum(c.source.count("assert ") for c in nb.cells if c.cell_type == "code")
    assert n_asserts >= 2, f"{path.name}: expected a few assert cells checking its claims"
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # the working tree first, so that the kernel (and the subprocesses it starts) import this
    # checkout's refgs and oracle whatever is installed; then the notebooks' folder (_helpers),
    # as the working directory is a temporary one
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(ROOT), str(NOTEBOOK_DIR)]
        + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    jupyter = tmp_path / ".jupyter"
    monkeypatch.setenv("JUPYTER_PATH", pin_kernel(jupyter))
    monkeypatch.setenv("JUPYTER_RUNTIME_DIR", str(jupyter / "runtime"))
    monkeypatch.setenv("IPYTHONDIR", str(tmp_path / ".ipython"))
    monkeypatch.chdir(tmp_path)
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=CELL_TIMEOUT_S,
                                     resources={"metadata": {"path": str(tmp_path)}})
    t0 = time.perf_counter()
    client.execute()
    seconds = time.perf_counter() - t0
    print(f"{path.name}: {seconds:.1f} s")
    assert seconds < TIME_LIMIT_S, f"{path.name} took {seconds:.1f} s (limit {TIME_LIMIT_S:.0f} s)"


# ---- docs/notebooks/_helpers.py ------------------------------------------------------------------

def test_fd_gradient_matches_a_known_derivative():
    x = np.linspace(-1.0, 2.0, 7).reshape(7, 1) * np.array([1.0, 0.5])
    c = np.arange(14.0).reshape(7, 2) - 5
    fd = helpers.fd_gradient(lambda v: float(np.sum(c * np.sin(v))), x)
    assert fd.shape == x.shape
    assert helpers.relative_error(c * np.cos(x), fd) < 1e-9
    # a wrong derivative is seen
    assert helpers.relative_error(c * np.cos(x) * 1.001, fd) > 1e-4


def test_relative_error_edge_cases():
    assert helpers.relative_error(np.zeros(3), np.zeros(3)) == 0.0
    assert helpers.relative_error(np.ones(3), np.zeros(3)) == float("inf")
    assert helpers.relative_error([1.0, 2.0], [1.0, 4.0]) == 0.5


def test_ellipse_axes_of_a_rotated_covariance():
    a = np.radians(30.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    w, h, angle = helpers.ellipse_axes(R @ np.diag([9.0, 1.0]) @ R.T, n_sigma=2.0)
    assert np.isclose(w, 12.0) and np.isclose(h, 4.0)
    assert np.isclose(np.mod(angle, 180.0), 30.0)


def test_clamp_bound_rejects_unknown_mode():
    with pytest.raises(ValueError, match="mode"):
        helpers.clamp_bound(None, "sphere", [1.0, 1.0, 1.0])


def test_text_table_columns_line_up():
    lines = helpers.text_table([("a", 1.5), ("longer", 2)], ["name", "value"]).splitlines()
    assert lines[0].index("value") == lines[2].index("1.500e+00") == lines[3].index("2")
