"""The oracle survives any backend (docs/spec/oracle.md ORC-11): isolation, verdicts, exit status.

Every hostile backend of oracle/meta/hostile.py runs in a worker process and gets its verdict --
timeout, crash or error -- with a message naming the cause, and the run completes within a bound.
Short time limits (5 s) and a 1 GiB memory limit keep this inside the default test budget.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

import refgs
from oracle.checks import get_check
from oracle.meta.hostile import HOSTILE
from oracle.protocol import BackendError
from oracle.runner import OK_STATUSES, Settings, check_backend, run_isolated
from oracle.wire import NotNumeric, decode, encode

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
TIMEOUT_S = 5
MEMORY_MIB = 1024
#: a hostile run (a worker start or two, at most two time limits) must end within this
RUN_BOUND_S = 60
#: two checks: the second runs in a fresh worker after the first one's crash
TWO = ("forward_generic", "forward_dtype")


def _cli(*args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "oracle", *args], cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_orc11_hostile_backend_gets_its_verdict(name):
    _, status, phrase = HOSTILE[name]
    names = TWO if status == "crash" else TWO[:1]       # a dead worker is replaced: run on
    t0 = time.monotonic()
    res = run_isolated(f"oracle.meta.hostile:{name}",
                       Settings(max_examples=3, timeout=TIMEOUT_S, memory_limit_mib=MEMORY_MIB),
                       checks=[get_check(n) for n in names])
    took = time.monotonic() - t0
    assert took < RUN_BOUND_S, took
    assert [r.status for r in res.results] == [status] * len(names), [
        (r.check.name, r.status, r.failure) for r in res.results]
    for r in res.results:
        assert phrase in r.failure["message"], r.failure["message"]
        assert r.failure["scene"] is not None        # the case it was on
    assert res.exit_status == 1


def test_orc11_cli_run_on_a_crashing_backend_completes_with_reports(tmp_path):
    rep = tmp_path / "rep"
    r = _cli("check", "--backend", "oracle.meta.hostile:segfaults", "--clause", "CNV-08,CNV-11",
             "--max-examples", "2", "--timeout", str(TIMEOUT_S), "--memory-limit", str(MEMORY_MIB),
             "--report", str(rep), "--quiet")
    assert r.returncode == 1, r.stdout + r.stderr
    data = json.loads((rep / "report.json").read_text())
    by = {c["name"]: c["status"] for c in data["checks"]}
    assert by == {"forward_intrinsics": "crash", "forward_pixel_centres": "crash",
                  "forward_dtype": "crash", "backward_dtype": "not provided"}, by
    crash = next(c for c in data["checks"] if c["status"] == "crash")
    assert "SIGSEGV" in crash["failure"]["message"] and "hostile.py" in crash["failure"]["message"]
    assert Path(crash["failure"]["reproducer"]).is_file()
    assert data["exit_status"] == 1 and (rep / "index.html").is_file()
    # replay runs the backend in a worker too: a backend that dies there is reported, not suffered
    again = _cli("replay", crash["failure"]["reproducer"], "--backend",
                 "oracle.meta.hostile:allocates_without_bound", "--memory-limit", str(MEMORY_MIB),
                 "--out", str(tmp_path / "replay"))
    assert again.returncode == 1 and "result: crash" in again.stdout, again.stdout + again.stderr
    assert "MemoryError" in again.stdout


def test_orc11_a_backend_that_cannot_load_is_one_line_and_exit_2(tmp_path):
    (tmp_path / "boom.py").write_text("raise RuntimeError('boom at import')\n")
    r = _cli("check", "--backend", "boom:backend", "--report", str(tmp_path / "rep"), cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "RuntimeError: boom at import" in lines[0], r.stderr
    assert not (tmp_path / "rep" / "report.json").exists()
    with pytest.raises(BackendError, match="cannot import module"):
        run_isolated("no_such_module_xyz:obj", Settings())


def test_orc11_check_backend_returns_the_report_dict(tmp_path):
    rep = check_backend("oracle.adapters.refgs_backend:refgs_float32",
                        Settings(max_examples=1, clauses=("CNV-08",), timeout=60,
                                 report_dir=str(tmp_path)))
    assert rep["exit_status"] == 0 and {c["status"] for c in rep["checks"]} <= set(OK_STATUSES)
    assert (tmp_path / "report.json").is_file() and (tmp_path / "index.html").is_file()


def test_orc11_wire_carries_arrays_and_containers_without_pickle():
    rng = np.random.default_rng(0)
    g = refgs.Gaussians(rng.normal(size=(3, 3)), rng.normal(size=(3, 3)), rng.normal(size=(3, 4)),
                        rng.normal(size=3), rng.normal(size=(3, 4, 3)))
    cam = refgs.Camera.look_at([0, 0, -4.0], [0, 0, 0], fx=40.0, width=8, height=6)
    cfg = refgs.RenderConfig(profile="gsplat", sh_degree=1, background=(0.1, 0.2, 0.3),
                             opacity_scale=np.array([0.5, 1.0, 2.0]))
    msg = {"args": [g, cam, cfg], "x": np.arange(4, dtype=np.float16), "b": np.array([True, False]),
           "n": np.int32(3), "s": "text"}
    back = decode(encode(msg))
    g2, cam2, cfg2 = back["args"]
    for f in refgs.Gaussians.FIELDS:
        np.testing.assert_array_equal(getattr(g2, f), getattr(g, f))
    np.testing.assert_array_equal(cam2.K, cam.K)
    assert (cam2.width, cam2.height, cfg2.profile, cfg2.sh_degree) == (8, 6, "gsplat", 1)
    np.testing.assert_array_equal(cfg2.opacity_scale, cfg.opacity_scale)
    assert back["x"].dtype == np.float16 and back["b"].dtype == bool and back["n"] == 3
    with pytest.raises(NotNumeric, match="object"):
        encode({"bad": np.array([object()])})


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs, self.ids = [], set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.srcs.append(a["src"])
        if "id" in a:
            self.ids.add(a["id"])


def test_orc13_page_of_a_planted_bug_shows_the_failing_case(tmp_path):
    rep = tmp_path / "rep"
    r = _cli("check", "--backend", "oracle.meta.planted:half_pixel_shift", "--clause", "CNV-08",
             "--max-examples", "3", "--timeout", "60", "--report", str(rep), "--quiet")
    assert r.returncode == 1, r.stdout + r.stderr
    page = (rep / "index.html").read_text()
    parser = _Images()
    parser.feed(page)
    parser.close()
    assert parser.srcs and all((rep / s).is_file() for s in parser.srcs), parser.srcs
    assert "pictures/forward_pixel_centres-image.png" in parser.srcs
    assert "check-forward_pixel_centres" in parser.ids
    assert "python -m oracle replay" in page and "Tolerance applied" in page
    assert "http://" not in page.replace('href="http', "") and "<script" not in page
    # replay prints the comparison and draws the same pictures for that case
    data = json.loads((rep / "report.json").read_text())
    fail = next(c for c in data["checks"] if c["name"] == "forward_pixel_centres")["failure"]
    out = tmp_path / "replay"
    again = _cli(*fail["replay"].split()[3:], "--out", str(out))
    assert again.returncode == 1 and "result: fail" in again.stdout, again.stdout + again.stderr
    assert (out / "forward_pixel_centres-image.png").is_file()


#: the headless browser of Debian's ``chromium`` package
CHROMIUM = Path("/usr/bin/chromium")
#: a rendered page has at least this many distinct colours (text, badges, pictures); a blank or
#: error page has one or two
MIN_COLOURS = 50


@pytest.mark.browser
def test_orc13_page_renders_in_a_headless_browser(tmp_path):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (Debian: apt-get install chromium)")
    from PIL import Image
    rep = tmp_path / "rep"
    r = _cli("check", "--backend", "oracle.meta.planted:half_pixel_shift", "--clause", "CNV-08",
             "--max-examples", "3", "--timeout", "60", "--report", str(rep), "--quiet")
    assert r.returncode == 1, r.stdout + r.stderr
    shot = tmp_path / "page.png"
    subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu",
                    "--disable-background-networking", "--hide-scrollbars", "--window-size=1100,1500",
                    f"--screenshot={shot}", (rep / "index.html").as_uri()],
                   capture_output=True, timeout=120, check=False)
    assert shot.is_file(), "chromium wrote no screenshot"
    img = np.asarray(Image.open(shot).convert("RGB"))
    colours = np.unique(img.reshape(-1, 3), axis=0).shape[0]
    assert colours >= MIN_COLOURS and img.std() > 10, (colours, float(img.std()))


def test_orc11_the_oracle_process_never_imports_the_backend(tmp_path, monkeypatch):
    (tmp_path / "probe_backend_xyz.py").write_text(
        "from oracle.adapters.refgs_backend import RefgsBackend\nb = RefgsBackend('inria', 'float64')\n")
    monkeypatch.chdir(tmp_path)
    res = run_isolated("probe_backend_xyz:b", Settings(max_examples=1, clauses=("CNV-08",), timeout=60))
    assert res.exit_status == 0 and res.backend.name == "refgs-inria-float64"
    assert "probe_backend_xyz" not in sys.modules
