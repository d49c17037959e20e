"""Per-view paired differences (refgs.analysis.per_view) on made-up records (FM-16)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from refgs.analysis.per_view import SUBSET_NOTE, main, per_view_markdown
from refgs.errors import ConfigError

VIEWS = ["a.png", "b.png", "c.png"]


def record(root: Path, method: str, seed: int, psnr: list, scene="desk", names=VIEWS,
           train=()) -> Path:
    f = root / f"{scene}_{method}_s{seed}"
    f.mkdir(parents=True)
    s = {"scene": f"/data/{scene}", "views": 3, "seed": seed, "method": method, "method_params": {}}
    (f / "config.json").write_text(json.dumps({"settings": s, "train_images": list(train)}))
    pv = [{"name": n, "psnr": p, "ssim": 0.5} for n, p in zip(names, psnr)]
    (f / "metrics.json").write_text(json.dumps({"psnr": float(np.mean(psnr)), "per_view": pv}))
    return f


@pytest.fixture()
def folders(tmp_path):
    base = [[40.0, 26.0, 27.0], [40.5, 25.5, 27.2], [39.5, 26.2, 26.9]]
    fm = [[36.0, 27.0, 27.5], [35.5, 26.9, 27.6], [36.2, 27.1, 27.0]]
    out = [record(tmp_path, "3dgs", s, base[s]) for s in range(3)]
    out += [record(tmp_path, "fm", s, fm[s]) for s in range(3)]
    return out, np.array(base), np.array(fm)


def cell(md: str, label: str) -> list[str]:
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| {label}"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_each_view_and_the_means_are_paired_over_seeds(folders):
    dirs, base, fm = folders
    md = per_view_markdown(dirs, "fm", "3dgs", subset=["b.png", "c.png"])
    for i, name in enumerate(VIEWS):
        d = fm[:, i] - base[:, i]
        ci = stats.ttest_1samp(d, 0.0).confidence_interval(0.95)
        c = cell(md, f"`{name}`")
        assert c[1] == f"{base[:, i].mean():.2f}" and c[2] == f"{fm[:, i].mean():.2f}"
        assert f"[{ci.low:+.2f}, {ci.high:+.2f}]" in c[3]
    d_all = fm.mean(axis=1) - base.mean(axis=1)
    assert cell(md, "mean of all views")[3].startswith(f"**{d_all.mean():+.2f}**")
    sub = cell(md, "mean of `b.png`, `c.png`")
    assert SUBSET_NOTE in sub[0]
    assert sub[3].startswith(f"**{(fm[:, 1:].mean(1) - base[:, 1:].mean(1)).mean():+.2f}**")


def test_bad_input_is_named(folders, tmp_path, capsys):
    dirs, _, _ = folders
    with pytest.raises(ConfigError, match="not test views"):
        per_view_markdown(dirs, "fm", "3dgs", subset=["z.png"])
    with pytest.raises(ConfigError, match="no seed has both 'dropgaussian' and '3dgs'"):
        per_view_markdown(dirs, "dropgaussian", "3dgs")
    with pytest.raises(ConfigError, match="--metric"):
        per_view_markdown(dirs, "fm", "3dgs", metric="psnr_db")
    other = record(tmp_path / "x", "fm", 0, [1.0, 2.0, 3.0])
    with pytest.raises(ConfigError, match="a second run of fm at seed 0"):
        per_view_markdown(dirs + [other], "fm", "3dgs")
    moved = record(tmp_path / "y", "fm", 5, [1.0, 2.0, 3.0], names=["a.png", "b.png", "d.png"])
    record(tmp_path / "y", "3dgs", 5, [1.0, 2.0, 3.0])
    with pytest.raises(ConfigError, match="test views differ"):
        per_view_markdown(dirs + [moved, tmp_path / "y" / "desk_3dgs_s5"], "fm", "3dgs")
    (dirs[0] / "metrics.json").write_text(json.dumps({"psnr": 1.0}))
    assert main([str(d) for d in dirs] + ["--method", "fm", "--baseline", "3dgs"]) == 2
    assert "metrics.json: no per_view list" in capsys.readouterr().err


def test_nearest_training_view_from_the_scene(tmp_path, shared_data):
    """desk: held-out frame 1 sits next to training frame 2 (camera centres from its model)."""
    names, train = ["input_0001.jpg", "input_0009.jpg"], ["input_0002.jpg", "input_0015.jpg"]
    dirs = [record(tmp_path, m, 0, [30.0, 26.0], names=names, train=train) for m in ("3dgs", "fm")]
    dirs += [record(tmp_path, m, 1, [31.0, 26.5], names=names, train=train) for m in ("3dgs", "fm")]
    md = per_view_markdown(dirs, "fm", "3dgs", scene=shared_data / "desk")
    near = cell(md, "`input_0001.jpg`")[1]
    assert near.startswith("`input_0002.jpg` (") and float(near.split("(")[1].rstrip(")")) < 0.05
    assert cell(md, "`input_0009.jpg`")[1].startswith("`input_0002.jpg` (0.5")
    with pytest.raises(ConfigError, match="no posed model image"):
        per_view_markdown(dirs, "fm", "3dgs", scene=shared_data / "fern")
