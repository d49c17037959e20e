"""``refgs flatness`` (FM-12) and ``refgs table`` (FM-13) on tiny runs of the test scene."""
from __future__ import annotations

import json

import numpy as np
import pytest

from refgs.cli import main
from refgs.analysis.flatness import flatness_curve
from refgs.analysis.tables import aggregate, load_run, markdown, method_label

from test_cli import run_cli, tiny_args, write_tiny_scene


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("fl")
    scene = write_tiny_scene(root / "scene")
    out = {}
    for method, seed, extra in (("3dgs", 3, ()), ("3dgs", 4, ()), ("fm", 3, ()),
                                ("fm", 4, ("--fm-perturb", "scale"))):
        d = root / f"{method}_{seed}_{len(extra)}"
        args = tiny_args(scene, d, 12, "--method", method, *extra)
        args[args.index("--seed") + 1] = str(seed)
        assert main(args) == 0
        out[(method, seed, extra)] = d
    return out


def test_fm12_flatness_curve(runs):
    from refgs.runs import load
    tr = load(runs[("fm", 3, ())]).trainer
    c = flatness_curve(tr, gammas=(0.0, 0.5, 3.0), seeds=3)
    assert c["p"] == 1.0 and c["alpha"] == 1.0 and c["clamp"] == "none"
    for split in ("train", "test"):
        all_ = np.asarray(c[split]["all"])
        assert all_.shape == (3, 3)
        assert np.all(all_[0] == all_[0, 0]) and c[split]["std"][0] == 0.0     # gamma 0: no noise
        assert c[split]["std"][1] > 0
    from refgs.metrics.psnr import psnr
    clean = np.mean([psnr(tr.render_view(v), v.image) for v in tr.test_views])
    assert c["test"]["mean"][0] == pytest.approx(clean, abs=1e-12)
    assert c["train"]["mean"][2] < c["train"]["mean"][0]          # a large gamma hurts
    again = flatness_curve(tr, gammas=(0.0, 0.5, 3.0), seeds=3)
    assert again["test"]["all"] == c["test"]["all"]                # seeded: reproducible
    tr_set = flatness_curve(tr, gammas=(3.0,), seeds=2, settings="training")
    assert tr_set["p"] == 0.3 and tr_set["clamp"] == "axis"
    assert tr_set["train"]["mean"][0] > c["train"]["mean"][2]      # p = 0.3 and the clamp: milder


def test_flatness_command_writes_json_csv_plot(runs, tmp_path, capsys):
    rc, out, err = run_cli(["flatness", runs[("3dgs", 3, ())], runs[("fm", 3, ())], "--gammas", "0",
                            "0.4", "--seeds", "2", "--out", tmp_path, "--quiet"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "flatness.json").read_text())
    assert len(doc["runs"]) == 2
    assert (tmp_path / "flatness.csv").read_text().count("\n") == 1 + 2 * 2
    assert (tmp_path / "flatness.png").stat().st_size > 0
    rc, _, err = run_cli(["flatness", runs[("fm", 3, ())], "--seeds", "0", "--out", tmp_path], capsys)
    assert rc == 2 and err.startswith("refgs: error: --seeds")


def test_fm13_method_labels():
    assert method_label({"method": "3dgs", "method_params": {}}) == "3dgs"
    assert method_label({"method": "dropgaussian", "method_params": {"fm": True, "gamma": 2.0}}) == "dropgaussian+fm"
    assert method_label({"method": "fm", "method_params": {"perturb": "rotation", "reinit": False,
                                                           "gamma": 2.0}}) == "fm[perturb=rotation,reinit=False]"
    # a parameter that does not apply to the chosen noise is not part of the label
    assert method_label({"method": "fm", "method_params": {"noise": "anisotropic",
                                                           "noise_fixed_sigma": 0.0}}) == "fm"
    assert method_label({"method": "fm", "method_params": {"noise": "iso_fixed",
                                                           "noise_fixed_sigma": 0.01}}) == \
        "fm[noise=iso_fixed,noise_fixed_sigma=0.01]"


def test_fm13_table_mean_std_over_seeds_and_scenes(runs, tmp_path, capsys):
    loaded = [load_run(d) for d in runs.values()]
    t = aggregate(loaded)
    rows = {r["method"]: r for r in t["per_scene"]}
    assert set(rows) == {"3dgs", "fm", "fm[perturb=scale]"}
    ps = [json.loads((runs[("3dgs", s, ())] / "metrics.json").read_text())["psnr"] for s in (3, 4)]
    assert rows["3dgs"]["psnr"]["mean"] == pytest.approx(np.mean(ps))
    assert rows["3dgs"]["psnr"]["std"] == pytest.approx(np.std(ps, ddof=1))
    assert rows["fm"]["psnr"]["std"] == 0.0 and rows["fm"]["psnr"]["n"] == 1
    assert rows["3dgs"]["lpips_vgg"] is None          # the tiny runs skip LPIPS
    # a second "scene": the same runs under another name -> over-scenes mean of the scene means
    other = [dict(r, scene="other", run=r["run"] + "'") for r in loaded]
    t2 = aggregate(loaded + other)
    over = {r["method"]: r for r in t2["over_scenes"]}
    assert over["3dgs"]["psnr"]["mean"] == pytest.approx(np.mean(ps)) and over["3dgs"]["psnr"]["n"] == 2
    assert "± " in markdown(t2)
    with pytest.raises(Exception, match="same scene, views, method and seed"):
        aggregate(loaded + loaded[:1])
    rc, out, _ = run_cli(["table", *runs.values(), "--out", tmp_path], capsys)
    assert rc == 0 and "| scene | views | method |" in out
    assert (tmp_path / "table.csv").read_text().startswith("level,scene,views,method,n,psnr_mean")
    assert (tmp_path / "table.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rc, _, err = run_cli(["table", tmp_path / "nope", "--out", tmp_path], capsys)
    assert rc == 2 and err.startswith("refgs: error:") and "config.json" in err


def test_fm13_baseline_deltas(runs, tmp_path, capsys):
    loaded = [load_run(d) for d in runs.values()]
    other = [dict(r, scene="other", run=r["run"] + "'") for r in loaded if r["label"] != "fm"]
    t = aggregate(loaded + other, baseline="fm")
    rows = {(r["scene"], r["method"]): r for r in t["per_scene"]}
    fern = loaded[0]["scene"]
    d = rows[(fern, "fm[perturb=scale]")]["delta"]["psnr"]
    assert d == rows[(fern, "fm[perturb=scale]")]["psnr"]["mean"] - rows[(fern, "fm")]["psnr"]["mean"]
    assert d != 0.0
    assert rows[(fern, "fm")]["delta"]["psnr"] == 0.0
    assert rows[("other", "3dgs")]["delta"]["psnr"] is None      # "other" has no fm row
    assert rows[(fern, "3dgs")]["delta"]["lpips_vgg"] is None    # no LPIPS in the tiny runs
    over = {r["method"]: r for r in t["over_scenes"]}
    assert over["3dgs"]["delta"]["psnr"] == over["3dgs"]["psnr"]["mean"] - over["fm"]["psnr"]["mean"]
    md = markdown(t)
    assert "Δpsnr vs fm" in md and f"{d:+.2f}" in md
    with pytest.raises(Exception, match="--baseline 'nope': no run has this method label"):
        aggregate(loaded, baseline="nope")
    rc, out, _ = run_cli(["table", *runs.values(), "--baseline", "fm", "--out", tmp_path], capsys)
    assert rc == 0 and "Δssim vs fm" in out
    header = (tmp_path / "table.csv").read_text().splitlines()[0]
    assert "psnr_delta_vs_fm,ssim_delta_vs_fm,lpips_vgg_delta_vs_fm,psnr_n_pairs" in header
    assert (tmp_path / "table.png").stat().st_size > 0
    # FM-16: 3dgs (seeds 3, 4) pairs with fm (seed 3) at seed 3 only; fm[perturb=scale] (seed 4)
    # has no seed in common with fm; the tiny runs have no LPIPS
    doc = json.loads((tmp_path / "table.json").read_text())
    comp = {(c["method"], c["metric"]): c for c in doc["comparisons"]}
    assert set(comp) == {("3dgs", "psnr"), ("3dgs", "ssim")}
    psnr = {k: json.loads((runs[k] / "metrics.json").read_text())["psnr"] for k in (("3dgs", 3, ()), ("fm", 3, ()))}
    c = comp[("3dgs", "psnr")]
    assert c["n_pairs"] == 1 and c["ci95"] is None and c["p_value"] is None and c["runs_needed"] is None
    assert c["mean_diff"] == pytest.approx(psnr[("3dgs", 3, ())] - psnr[("fm", 3, ())])
    reasons = {u["method"]: u["reason"] for u in doc["unpaired"]}
    assert "no seed in common" in reasons["fm[perturb=scale]"] and "missing" in reasons["3dgs"]
    assert "n = 1: no interval" in out and (tmp_path / "forest.png").stat().st_size > 0
    rc, _, err = run_cli(["table", *runs.values(), "--baseline", "nope", "--out", tmp_path / "x"], capsys)
    assert rc == 2 and "--baseline 'nope'" in err and not (tmp_path / "x").exists()
