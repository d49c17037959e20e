"""``refgs figures`` (FM-14) on tiny runs of the test scene."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image

from refgs.cli import main
from refgs.analysis.figures import load_figure_run, reinit_iterations

from test_cli import run_cli, tiny_args, write_tiny_scene


@pytest.fixture(scope="module")
def fig_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("figs")
    scene = write_tiny_scene(root / "scene")
    out = {}
    for name, extra in (("fm", ("--method", "fm", "--fm-reinit-interval", "5")),
                        ("fm_noreinit", ("--method", "fm", "--fm-no-reinit")),
                        ("3dgs", ())):
        d = root / name
        assert main(tiny_args(scene, d, 12, *extra)) == 0
        out[name] = d
    flat = root / "flat"
    assert main(["flatness", str(out["fm"]), "--gammas", "0", "1", "--seeds", "2", "--out",
                 str(flat), "--quiet"]) == 0
    return out, flat


def test_fm14_reinit_iterations():
    s = {"method": "fm", "iters": 10000, "method_params": {"reinit": True, "reinit_interval": 1000}}
    assert reinit_iterations(s) == list(range(1000, 9001, 1000))
    assert reinit_iterations({**s, "method_params": {"reinit": False}}) == []
    assert reinit_iterations({"method": "3dgs", "iters": 10000, "method_params": {}}) == []
    assert reinit_iterations({"method": "dropgaussian", "iters": 3000,
                              "method_params": {"fm": True}}) == [1000, 2000]


def test_fm14_figures_command(fig_runs, tmp_path, capsys):
    runs, flat = fig_runs
    # a run whose renders were removed is rendered from its checkpoint
    shutil.rmtree(runs["3dgs"] / "renders")
    out = tmp_path / "figs"
    rc, stdout, err = run_cli(["figures", *runs.values(), "--flatness", flat, "--out", out], capsys)
    assert rc == 0, err
    names = {p.name for p in out.iterdir()}
    assert names == {"renders_fm.png", "renders_fm_noreinit.png", "renders_3dgs.png",
                     "psnr_trajectories.png", "gaussians.png", "flatness.png", "index.md"}
    for n in names - {"index.md"}:
        assert str(out / n) in stdout
        with Image.open(out / n) as im:
            assert im.size[0] > 300 and im.size[1] > 200
            assert np.asarray(im.convert("L")).std() > 1          # not a blank canvas
    index = (out / "index.md").read_text()
    assert "fm[reinit=False] s3" in index and "fm[reinit_interval=5] s3" in index
    assert load_figure_run(runs["fm_noreinit"])["label"] == "fm[reinit=False] s3"


def test_fm14_figures_errors(fig_runs, tmp_path, capsys):
    runs, _ = fig_runs
    rc, _, err = run_cli(["figures", tmp_path / "nope", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and err.startswith("refgs: error:") and "config.json" in err
    assert not (tmp_path / "o").exists()                     # nothing written on bad input
    rc, _, err = run_cli(["figures", runs["fm"], "--flatness", runs["fm"] / "metrics.json",
                          "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "refgs flatness" in err and not (tmp_path / "o").exists()
    rc, _, err = run_cli(["figures", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "RUN_DIR" in err


def test_record_keeps_what_tables_and_curves_need(fig_runs, tmp_path, capsys):
    """refgs record: config/metrics byte for byte, the history rounded, flatness outputs as
    they are; refgs table and refgs figures take the records (figures without renders)."""
    import json

    from refgs.analysis.records import RECORD_DECIMALS
    runs, flat = fig_runs
    rec = tmp_path / "records"
    rc, stdout, err = run_cli(["record", runs["fm"], runs["fm_noreinit"], flat, "--out", rec], capsys)
    assert rc == 0, err
    assert {p.name for p in rec.iterdir()} == {"fm", "fm_noreinit", "flat"}
    for name in ("fm", "fm_noreinit"):
        for f in ("config.json", "metrics.json"):
            assert (rec / name / f).read_bytes() == (runs[name] / f).read_bytes()
        full = json.loads((runs[name] / "history.json").read_text())
        kept = json.loads((rec / name / "history.json").read_text())
        assert kept.keys() == full.keys()
        for key, values in full.items():
            d = RECORD_DECIMALS.get(key)
            assert kept[key] == ([round(v, d) for v in values] if d is not None else values)
        assert json.loads((rec / name / "record.json").read_text())["source"] == str(runs[name])
    assert (rec / "flat" / "flatness.json").read_bytes() == (flat / "flatness.json").read_bytes()
    out = tmp_path / "figs"
    rc, _, err = run_cli(["figures", rec / "fm", rec / "fm_noreinit", "--flatness", rec / "flat",
                          "--out", out], capsys)
    assert rc == 0, err
    assert {p.name for p in out.iterdir()} == {"psnr_trajectories.png", "gaussians.png",
                                               "flatness.png", "index.md"}
    assert "no renders of" in (out / "index.md").read_text()
    rc, stdout, err = run_cli(["table", rec / "fm", rec / "fm_noreinit", "--out", tmp_path / "t"],
                              capsys)
    assert rc == 0 and "fm[reinit=False]" in stdout


def test_record_refuses_unfinished_runs_before_writing(fig_runs, tmp_path, capsys):
    runs, _ = fig_runs
    bad = tmp_path / "unfinished"
    bad.mkdir()
    (bad / "config.json").write_text((runs["fm"] / "config.json").read_text())
    rec = tmp_path / "records"
    rc, _, err = run_cli(["record", runs["fm"], bad, "--out", rec], capsys)
    assert rc == 2 and "metrics.json" in err and "unfinished" in err
    assert not rec.exists()                                   # nothing written on bad input
    rc, _, err = run_cli(["record", tmp_path / "nope", "--out", rec], capsys)
    assert rc == 2 and "not a folder" in err
