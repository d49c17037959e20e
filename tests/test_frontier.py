"""refgs frontier: test metrics against training time and Gaussians, from a grid's records
(refgs.analysis.frontier, docs/compact.md)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from refgs.analysis.frontier import UNRECORDED_CPU, frontier_points, plot, record_cpu
from refgs.cli import main as refgs_main
from refgs.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
GRID = ROOT / "experiments" / "compact.toml"
RECORDS = ROOT / "results" / "records"


def test_the_points_are_the_reported_records_of_the_grids_scenes():
    points = frontier_points(GRID, RECORDS)
    cells = {(p.scene, p.views, p.method) for p in points}
    # the included campaign's paper-protocol runs of the grid's (scene, views) are there ...
    assert ("fern", 3, "fm") in cells and ("bonsai", 12, "3dgs") in cells
    # ... and nothing of the campaign's other scenes, nor the trial runs made outside the grid
    assert all((p.scene, p.views) in {("fern", 3), ("bonsai", 12)} for p in points)
    assert not any("trial" in p.record for p in points)
    for p in points:
        history = json.loads((RECORDS / p.record / "history.json").read_text())
        assert p.loop_minutes == pytest.approx(np.sum(history["iter_seconds"]) / 60.0)
        metrics = json.loads((RECORDS / p.record / "metrics.json").read_text())
        assert p.gaussians == metrics["n_gaussians"] and p.metrics["psnr"] == metrics["psnr"]


def test_the_machine_of_a_record_is_its_numba_target():
    assert record_cpu({"provenance": {"float_environment": {"numba_cpu": "znver3"}}}) == "znver3"
    assert record_cpu({"provenance": {}}) == UNRECORDED_CPU
    assert record_cpu({}) == UNRECORDED_CPU


def test_refgs_frontier_writes_the_figure(tmp_path, capsys):
    out = tmp_path / "f.png"
    refgs_main(["frontier", str(GRID), "--records", str(RECORDS), "--out", str(out)])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "written to" in capsys.readouterr().out


def test_no_records_is_a_one_line_error(tmp_path):
    (tmp_path / "records").mkdir()
    with pytest.raises(ConfigError, match="no records"):
        plot(frontier_points(GRID, tmp_path / "records"), tmp_path / "f.png")
