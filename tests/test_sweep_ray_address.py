"""``refgs sweep --executor ray`` with RAY_ADDRESS where no cluster listens: one line naming the
address, well within 30 s (refgs.sweep.executors.check_ray, ``--ray-timeout``)."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from refgs.sweep.executors import DEFAULT_RAY_TIMEOUT_S, ray_endpoint

#: the acceptance bound: a mistyped address fails within this many seconds
LIMIT_S = 30.0
#: a port where nothing listens on this machine (port 1, tcpmux, is never served here)
NOWHERE = "127.0.0.1:1"


def test_ray_endpoint_parses_the_address_forms():
    assert ray_endpoint("127.0.0.1:6379") == ("127.0.0.1", 6379)
    assert ray_endpoint("ray://head.cluster:10001") == ("head.cluster", 10001)
    assert ray_endpoint("[::1]:6379") == ("::1", 6379)
    assert ray_endpoint("auto") is None and ray_endpoint("local") is None
    assert DEFAULT_RAY_TIMEOUT_S < LIMIT_S


def test_sweep_with_no_cluster_at_the_address_fails_in_one_line(tmp_path):
    pytest.importorskip("ray", reason="the ray executor needs ray (pip install 'refgs[ray]')")
    (tmp_path / "scene").mkdir()
    grid = tmp_path / "g.toml"
    grid.write_text('scene = "scene"\nviews = 3\niters = 2\nbackend = "reference"\n')
    env = {**os.environ, "RAY_ADDRESS": NOWHERE}
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "refgs", "sweep", str(grid), "--out",
                        str(tmp_path / "D"), "--executor", "ray"], capture_output=True, text=True,
                       env=env, timeout=120, cwd=tmp_path)
    seconds = time.perf_counter() - t0
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    assert r.returncode != 0 and seconds < LIMIT_S, (r.returncode, seconds, lines)
    assert len(lines) == 1 and lines[0].startswith("refgs: error:"), lines
    assert NOWHERE in lines[0] and "--ray-timeout" in lines[0], lines[0]
    assert not Path(tmp_path / "D").exists()
