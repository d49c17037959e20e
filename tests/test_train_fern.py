"""A short fern 3-view run (docs/spec/training.md TRN-01..TRN-10, TRN-12).

With ``--backend fast`` (numba) it is part of the default suite (about 1.5 minutes on 2 cores);
with the numpy reference it is behind the ``slow`` marker (``pytest -m slow
tests/test_train_fern.py``: about 20 minutes, 4 s per iteration on 504 x 378 images, TRN-12).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

DATA = Path(os.environ.get("REFGS_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
FERN = DATA / "fern"
ITERS = 300

pytestmark = [pytest.mark.skipif(not FERN.is_dir(), reason="needs shared/data/fern")]


def _has_numba() -> bool:
    import importlib.util
    return importlib.util.find_spec("numba") is not None


@pytest.mark.parametrize("backend", [
    pytest.param("fast", marks=pytest.mark.skipif(not _has_numba(), reason="needs numba")),
    pytest.param("reference", marks=pytest.mark.slow)])
def test_fern_three_views(tmp_path, backend):
    from refgs.cli import build_parser, config_from_args
    from refgs.data.init import init_gaussians_from_points
    from refgs.data.pointcloud import read_ply
    from refgs.metrics.psnr import psnr
    from refgs.train.trainer import Trainer
    from refgs.backends import get_backend
    from refgs.runs import load_views, train

    out = tmp_path / "fern3"
    # densification brought forward (from 100 every 100: at 200) so that this short run densifies
    args = build_parser().parse_args([
        "train", "--scene", str(FERN), "--views", "3", "--iters", str(ITERS), "--seed", "0",
        "--out", str(out), "--densify-from", "100", "--eval-every", "100", "--quiet",
        "--backend", backend])
    cfg = config_from_args(args)
    run = train(cfg, out, progress=False)

    config = json.loads((run / "config.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    history = json.loads((run / "history.json").read_text())
    assert config["train_images"] == ["IMG_4027.png", "IMG_4036.png", "IMG_4045.png"]
    assert config["test_images"] == ["IMG_4026.png", "IMG_4034.png", "IMG_4042.png"]
    assert config["image_size"] == [504, 378]
    assert config["n_init_points"] > 100          # triangulated from the 3 training views
    assert metrics["iterations"] == ITERS and len(metrics["per_view"]) == 3
    for key in ("lpips_vgg", "lpips_vgg_official", "lpips_alex"):
        assert metrics[key] is not None and 0 < metrics[key] < 1
    # densification at 200 changed the number of Gaussians
    assert history["n_gaussians"][210] != history["n_gaussians"][0]
    # the fit improves: training PSNR and test PSNR against the initial cloud
    train_psnr = np.asarray(history["train_psnr"])
    assert train_psnr[-30:].mean() > train_psnr[:30].mean() + 2.0
    _, _, _, train_views, test_views = load_views(cfg)
    pts, cols = read_ply(run / "init_points.ply")
    init = init_gaussians_from_points(pts, cols, 3)
    t0 = Trainer(cfg, train_views, test_views, init.to_dict(), 1.0, get_backend("reference"))
    init_psnr = np.mean([psnr(t0.render_view(v), v.image) for v in test_views])
    assert metrics["psnr"] > init_psnr + 1.0, (metrics["psnr"], init_psnr)
    assert sorted(p.name for p in (run / "renders" / "test").iterdir()) == [
        "IMG_4026.png", "IMG_4034.png", "IMG_4042.png"]


@pytest.mark.slow
def test_demo_command(tmp_path, capsys):
    """`refgs demo` end to end with a few iterations (builds the demo scene on first use): both
    runs, the table and the comparison picture."""
    from refgs.analysis.demo import DEMO_METHODS, FIGURE_FILE
    from refgs.cli import main

    assert main(["demo", "--out", str(tmp_path / "demo"), "--iters", "6"]) == 0
    out = capsys.readouterr().out
    assert "PSNR" in out and "picture:" in out
    for method in DEMO_METHODS:
        metrics = json.loads((tmp_path / "demo" / method / "metrics.json").read_text())
        assert metrics["iterations"] == 6 and metrics["lpips_vgg"] is not None
        assert method in out
    assert (tmp_path / "demo" / FIGURE_FILE).stat().st_size > 10_000
