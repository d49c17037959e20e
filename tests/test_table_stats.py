"""``refgs table --baseline``: paired statistics against scipy.stats computed directly (FM-16).

The runs are made-up run folders (config.json + metrics.json with chosen values), so every test
takes well under a second apart from the one end-to-end call that draws the plots.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats as sps

from refgs.analysis.stats import (MAX_RUNS_NEEDED, NO_INTERVAL, POWER, ZERO_SPREAD, compare, power,
                                  runs_needed)
from refgs.analysis.tables import load_run
from refgs.cli import main

COMPARISON_KEYS = {"scene", "views", "method", "baseline", "metric", "n_pairs", "mean_diff", "ci95",
                   "p_value", "runs_needed"}
METRICS = ("psnr", "ssim", "lpips_vgg")


def make_run(root, name, *, scene="fern", views=3, method="3dgs", seed=0, metrics, params=None,
             **settings):
    """A finished-run folder with only what ``refgs table`` reads."""
    d = root / name
    d.mkdir(parents=True)
    s = {"scene": f"/data/{scene}", "views": views, "iters": 10000, "seed": seed, "method": method,
         "method_params": params or {}, "backend": "fast", "checkpoint_every": 500, "lpips": True,
         "densify": {"start": 500, "interval": 100}}
    s.update(settings)
    (d / "config.json").write_text(json.dumps({"settings": s}))
    (d / "metrics.json").write_text(json.dumps(metrics))
    return d


#: Made-up truth: (PSNR offset, its spread over seeds) per method; fm is clearly better than 3dgs,
#: dropgaussian hardly differs.
EFFECTS = {"3dgs": (0.0, 0.0), "dropgaussian": (0.05, 0.4), "fm": (1.0, 0.1)}


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """2 scenes x 3 methods x 5 seeds; returns (root, {(scene, method, seed): metrics})."""
    root = tmp_path_factory.mktemp("grid")
    rng = np.random.default_rng(7)
    values = {}
    for scene, base_psnr in (("fern", 19.0), ("horns", 17.5)):
        seed_effect = rng.normal(0.0, 0.5, 5)              # shared by the methods of one seed
        for method, (off, sd) in EFFECTS.items():
            for seed in range(5):
                p = base_psnr + seed_effect[seed] + off + (rng.normal(0.0, sd) if sd else 0.0)
                m = {"psnr": float(p), "ssim": float(0.6 + 0.02 * (p - 19) + rng.normal(0, 0.002)),
                     "lpips_vgg": float(0.27 - 0.01 * (p - 19) + rng.normal(0, 0.001))}
                values[(scene, method, seed)] = m
                make_run(root, f"{scene}3_{method}_s{seed}", scene=scene, method=method, seed=seed,
                         metrics=m, params={"r_max": 0.2} if method == "dropgaussian" else None)
    return root, values


def table(run_dirs, out, *extra) -> dict:
    assert main(["table", *map(str, run_dirs), "--out", str(out), *extra]) == 0
    return json.loads((out / "table.json").read_text())


def test_fm16_paired_statistics_match_scipy(grid, tmp_path, capsys):
    root, values = grid
    doc = table(sorted(root.iterdir()), tmp_path, "--baseline", "3dgs")
    comps = doc["comparisons"]
    assert len(comps) == 2 * 2 * 3                 # scenes x methods other than 3dgs x metrics
    for c in comps:
        assert set(c) == COMPARISON_KEYS and c["baseline"] == "3dgs" and c["views"] == 3
        a = np.array([values[(c["scene"], c["method"], s)][c["metric"]] for s in range(5)])
        b = np.array([values[(c["scene"], "3dgs", s)][c["metric"]] for s in range(5)])
        d = a - b                                          # method - baseline, own units
        lo, hi = sps.t.interval(0.95, 4, loc=d.mean(), scale=sps.sem(d))
        assert c["n_pairs"] == 5
        assert c["mean_diff"] == pytest.approx(d.mean(), rel=1e-12)
        assert c["ci95"] == pytest.approx([lo, hi], rel=1e-10)
        assert c["p_value"] == pytest.approx(sps.ttest_rel(a, b).pvalue, rel=1e-10)
        assert c["runs_needed"] is None or (isinstance(c["runs_needed"], int) and c["runs_needed"] >= 2)
    det = {(d["scene"], d["method"], d["metric"]): d for d in doc["details"]}
    assert all(d["wilcoxon_p"] is None and d["seeds"] == [0, 1, 2, 3, 4] for d in det.values())
    by = {(c["scene"], c["method"], c["metric"]): c for c in comps}
    assert by[("fern", "fm", "psnr")]["ci95"][0] > 0          # clearly better: the CI excludes 0
    assert by[("fern", "fm", "lpips_vgg")]["mean_diff"] < 0   # lower LPIPS: a negative difference
    need = {m: by[("fern", m, "psnr")]["runs_needed"] for m in ("fm", "dropgaussian")}
    assert 2 <= need["fm"] < need["dropgaussian"]          # a clear effect needs fewer seeds
    # pooled over the two scenes: the per-scene mean differences, their mean, a t interval over scenes
    pooled = {(p["method"], p["metric"]): p for p in doc["pooled"]}
    assert len(pooled) == 2 * 3
    p = pooled[("fm", "psnr")]
    per = [by[(s, "fm", "psnr")]["mean_diff"] for s in ("fern", "horns")]
    assert p["scene"] == "all" and p["scenes"] == ["fern", "horns"] and p["per_scene_diffs"] == per
    assert p["mean_diff"] == pytest.approx(np.mean(per))
    assert p["ci95"] == pytest.approx(sps.t.interval(0.95, 1, loc=np.mean(per), scale=sps.sem(per)))
    assert p["p_value"] == pytest.approx(sps.ttest_1samp(per, 0.0).pvalue)
    # the outputs: a paper table with the CI beside each delta, CIs that exclude 0 in bold
    md = (tmp_path / "table.md").read_text()
    f = by[("fern", "fm", "psnr")]
    assert f"**{f['mean_diff']:+.2f}** [{f['ci95'][0]:+.2f}, {f['ci95'][1]:+.2f}]" in md
    for c in comps:
        k = 2 if c["metric"] == "psnr" else 3
        cell = f"{c['mean_diff']:+.{k}f}** [" if c["ci95"][0] > 0 or c["ci95"][1] < 0 else \
            f"| {c['mean_diff']:+.{k}f} ["
        assert cell in md, c
    assert "Over scenes" in md and "p (Wilcoxon)" in md
    rows = (tmp_path / "table.csv").read_text().splitlines()
    assert "psnr_ci95_lo" in rows[0] and "lpips_vgg_runs_needed" in rows[0]
    assert len(rows) == 1 + 2 * 3 + 3                        # per-scene rows, then over-scenes rows
    for name in ("table.png", "forest.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()


def test_fm16_one_pair_has_no_interval(tmp_path, capsys):
    runs = [make_run(tmp_path, "b", method="3dgs", seed=2,
                     metrics={"psnr": 19.3, "ssim": 0.62, "lpips_vgg": 0.27}),
            make_run(tmp_path, "m", method="fm", seed=2,
                     metrics={"psnr": 21.3, "ssim": 0.70, "lpips_vgg": 0.23})]
    doc = table(runs, tmp_path / "out", "--baseline", "3dgs")
    c = {c["metric"]: c for c in doc["comparisons"]}
    assert c["psnr"] == {"scene": "fern", "views": 3, "method": "fm", "baseline": "3dgs", "metric": "psnr",
                         "n_pairs": 1, "mean_diff": pytest.approx(2.0), "ci95": None, "p_value": None,
                         "runs_needed": None}
    assert c["lpips_vgg"]["mean_diff"] == pytest.approx(-0.04)
    md = (tmp_path / "out" / "table.md").read_text()
    assert f"+2.00 ({NO_INTERVAL})" in md
    assert (tmp_path / "out" / "forest.png").stat().st_size > 0
    capsys.readouterr()


def test_fm16_only_matched_seeds_pair(tmp_path):
    rng = np.random.default_rng(3)
    base, meth = rng.normal(20, 0.5, 5), rng.normal(20.8, 0.5, 5)
    runs = [make_run(tmp_path, f"b{s}", method="3dgs", seed=s, metrics={"psnr": base[s]}) for s in range(5)]
    runs += [make_run(tmp_path, f"m{s}", method="fm", seed=s, metrics={"psnr": meth[s]})
             for s in range(5) if s != 2]                       # fm is missing seed 2
    runs += [make_run(tmp_path, "x", method="fm", params={"perturb": "scale"}, seed=9,
                      metrics={"psnr": 20.0})]                  # no seed in common
    out = compare([load_run(r) for r in runs], ["psnr"], "3dgs")
    [c] = out["comparisons"]
    keep = [0, 1, 3, 4]
    assert c["n_pairs"] == 4 and out["details"][0]["seeds"] == keep
    r = sps.ttest_rel(meth[keep], base[keep])
    assert c["p_value"] == pytest.approx(r.pvalue, rel=1e-10)
    assert c["ci95"] == pytest.approx(list(r.confidence_interval(0.95)), rel=1e-10)
    [u] = out["unpaired"]
    assert u["method"] == "fm[perturb=scale]" and "no seed in common" in u["reason"]


def test_fm16_runs_needed_power():
    # textbook sample sizes of the two-sided one-sample t-test, alpha 0.05, power 0.8
    # (Cohen 1988; G*Power): effect size 0.5 -> 34, 0.8 -> 15, 1.0 -> 10
    assert [runs_needed(e, 1.0) for e in (0.5, 0.8, 1.0)] == [34, 15, 10]
    # a larger spread of the paired differences needs more runs; none for no effect
    assert runs_needed(1.0, 0.5) < runs_needed(1.0, 1.0) < runs_needed(1.0, 2.0)
    assert runs_needed(0.0, 1.0) is None and runs_needed(1e-3, 1.0) is None     # > MAX_RUNS_NEEDED
    assert runs_needed(0.05, 1.0) <= MAX_RUNS_NEEDED
    # the noncentral-t power against a simulation of the paired t-test
    rng = np.random.default_rng(0)
    n, effect, trials = 34, 0.5, 20000
    x = rng.normal(effect, 1.0, (trials, n))
    rejected = sps.ttest_1samp(x, 0.0, axis=1).pvalue < 0.05
    assert power(n, effect) == pytest.approx(rejected.mean(), abs=0.015)
    assert power(n, effect) >= POWER > power(n - 1, effect)


def test_fm16_spread_wilcoxon_and_zero_spread(tmp_path):
    def runs_with(diffs, tag):
        out = []
        for s, d in enumerate(diffs):
            out.append(make_run(tmp_path, f"{tag}b{s}", method="3dgs", seed=s, metrics={"psnr": 20.0 + s}))
            out.append(make_run(tmp_path, f"{tag}m{s}", method="fm", seed=s, metrics={"psnr": 20.0 + s + d}))
        return [load_run(r) for r in out]

    narrow = np.array([0.9, 1.1, 1.0, 0.95, 1.05, 1.02, 0.98])
    wide = 1.0 + 4.0 * (narrow - 1.0)                           # same mean, 4x the spread
    c_n = compare(runs_with(narrow, "n"), ["psnr"], "3dgs")
    c_w = compare(runs_with(wide, "w"), ["psnr"], "3dgs")
    assert c_n["comparisons"][0]["runs_needed"] < c_w["comparisons"][0]["runs_needed"]
    d = c_w["details"][0]
    assert d["wilcoxon_p"] == pytest.approx(sps.wilcoxon(wide).pvalue)          # 7 pairs >= 6
    flat = compare(runs_with([0.5] * 3, "z"), ["psnr"], "3dgs")
    assert flat["comparisons"][0]["ci95"] is None and flat["details"][0]["note"] == ZERO_SPREAD


def test_fm16_conditions_and_records(tmp_path, capsys):
    from refgs.analysis.records import record_runs

    m = {"psnr": 20.0}
    runs = [make_run(tmp_path, "b0", seed=0, metrics=m),
            make_run(tmp_path, "f0", method="fm", seed=0, metrics={"psnr": 21.0}, checkpoint_every=0),
            make_run(tmp_path, "b0_short", seed=0, iters=3000, metrics=m),
            make_run(tmp_path, "f0_short", method="fm", seed=0, iters=3000, metrics={"psnr": 20.5})]
    out = compare([load_run(r) for r in runs], ["psnr"], "3dgs")
    got = {c["scene"]: c["mean_diff"] for c in out["comparisons"]}
    # iters splits the runs into two conditions; checkpoint_every (bookkeeping) does not
    assert got == {"fern (iters=10000)": pytest.approx(1.0), "fern (iters=3000)": pytest.approx(0.5)}
    # a record folder gives what its run folder gives
    for r in runs:
        (r / "history.json").write_text(json.dumps({"train_loss": [0.5, 0.25]}))
    recs = record_runs(runs, tmp_path / "records")
    doc = table(recs, tmp_path / "out", "--baseline", "3dgs", "--metrics", "psnr")
    assert doc["comparisons"] == out["comparisons"]
    capsys.readouterr()


def test_fm16_bad_metric_is_a_one_line_error(tmp_path, capsys):
    runs = [make_run(tmp_path, "b", seed=0, metrics={"psnr": "high"}),
            make_run(tmp_path, "m", method="fm", seed=0, metrics={"psnr": 21.0})]
    assert main(["table", *map(str, runs), "--baseline", "3dgs", "--metrics", "psnr",
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("refgs: error:") and "metrics.json" in err and "psnr" in err
    assert not (tmp_path / "out").exists()


def test_forest_axis_spans_the_scene_intervals_not_a_wide_pooled_one():
    """forest.png: the axis holds 0, every mean and the per-scene CIs; a pooled CI over a few
    scenes (t with 1-2 degrees of freedom) is cut, not allowed to squash the scene rows."""
    from refgs.analysis.tables import FOREST_MARGIN, forest_limits
    rows = [{"mean_diff": 0.5, "ci95": [0.2, 0.9]}, {"mean_diff": -1.5, "ci95": [-2.0, -1.0]},
            {"mean_diff": -0.5, "ci95": [-13.9, 12.9], "n_scenes": 2}, None,
            {"mean_diff": 3.0, "ci95": None}]
    lo, hi = forest_limits(rows)
    pad = FOREST_MARGIN * 5.0
    assert np.isclose(lo, -2.0 - pad) and np.isclose(hi, 3.0 + pad)
    assert forest_limits([None]) == (-1.0, 1.0)
