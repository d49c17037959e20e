"""The reports of experiments/paper_main.toml and paper_followups.toml (refgs.analysis.report,
declared by their [report] tables), the qualitative figure (refgs.analysis.qualitative) and the
flatness curves over seeds (refgs.analysis.flatness), on made-up records, renders and flatness
files (FM-12, FM-14, FM-15, FM-16)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import stats

from refgs.analysis import qualitative
from refgs.analysis.cost import cost_markdown, segments, union_seconds
from refgs.analysis.figures import make_figures
from refgs.analysis.flatness import curve_key, group_over_seeds
from refgs.analysis.flatness_drops import flatness_markdown
from refgs.analysis.report import (SUMMARY_MARKERS, load_runs, markers, report_markdown,
                                   reports_beside, split_document)
from refgs.analysis.report_spec import load_report, made_by
from refgs.analysis.report_tables import MISSING, NO_PAIRS, paper_table
from refgs.analysis.stats import runs_needed
from refgs.analysis.summary import summary_markdown
from refgs.cli import main as refgs_main
from refgs.errors import ConfigError

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
MAIN = load_report(EXPERIMENTS / "paper_main.toml")
FOLLOWUPS = load_report(EXPERIMENTS / "paper_followups.toml")
#: The training code the main campaign accepts first.
CODE = MAIN.code[0]


def campaign_markdown(root: Path) -> str:
    return report_markdown(MAIN, root)


def followups_markdown(root: Path) -> str:
    return report_markdown(FOLLOWUPS, root)


def load_campaign(root: Path):
    return load_runs(root, MAIN)

GRID_COMMAND = ["refgs", "run-one", "/elsewhere/repo/experiments/paper_main.toml", "--out",
                "/elsewhere/repo/runs/paper_main", "--name"]


def write_record(root: Path, scene="fern", views=3, method="fm", seed=0, psnr=20.0, ssim=0.7,
                 lpips=0.2, command=None, **settings) -> Path:
    name = f"{scene}_v{views}_{method}_s{seed}"
    folder = root / name
    folder.mkdir(parents=True)
    s = {"scene": f"/data/{scene}", "views": views, "iters": 10000, "seed": seed, "method": method,
         "method_params": {}, "backend": "fast", "images": "images_8", "checkpoint_every": 500,
         **settings}
    cmd = GRID_COMMAND + [name] if command is None else command
    config = {"command": cmd, "settings": s, "started": "2026-12-05T10:00:00+0000"}
    if command is None:                           # the main grid's run, by code it accepts
        config["provenance"] = {"source_hash": CODE}
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "metrics.json").write_text(json.dumps({"psnr": psnr, "ssim": ssim, "lpips_vgg": lpips}))
    (folder / "history.json").write_text(json.dumps({"iter_seconds": [1.0] * 60}))
    return folder


def rows(md: str, first_head: str) -> dict[tuple, list[str]]:
    """{(scene, views, method-or-difference): cells} of the table whose header starts so."""
    table = md.split(f"| {first_head}", 1)[1].split("\n\n", 1)[0]
    body = [ln for ln in table.splitlines()[2:] if ln.startswith("| ")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in body]
    return {tuple(c[:3]): c for c in cells}


def ci_text(d, digits):
    res = stats.ttest_1samp(np.asarray(d), 0.0)
    ci = res.confidence_interval(0.95)
    m = f"{np.mean(d):+.{digits}f}"
    m = f"**{m}**" if ci.low > 0 or ci.high < 0 else m
    return f"{m} [{ci.low:+.{digits}f}, {ci.high:+.{digits}f}]", res.pvalue


@pytest.fixture()
def records(tmp_path):
    """fern: 3DGS, DropGaussian and FM at seeds 0, 1, 2; desk: FM and DropGaussian at seed 0."""
    root = tmp_path / "records"
    fm, dg, base = [21.0, 21.4, 20.9], [20.5, 20.6, 20.7], [19.0, 19.5, 19.3]
    for seed in range(3):
        write_record(root, method="fm", seed=seed, psnr=fm[seed], ssim=0.70 + 0.01 * seed,
                     lpips=0.23)
        write_record(root, method="dropgaussian", seed=seed, psnr=dg[seed], ssim=0.68,
                     lpips=0.25 - 0.01 * seed)
        write_record(root, method="3dgs", seed=seed, psnr=base[seed], ssim=0.62 + 0.02 * seed,
                     lpips=0.27)
    write_record(root, scene="desk", method="fm", psnr=18.0, ssim=0.60, lpips=0.30)
    write_record(root, scene="desk", method="dropgaussian", psnr=17.5, ssim=0.61, lpips=0.31)
    return root, {"fm": fm, "dropgaussian": dg, "3dgs": base}


def test_complete_cell_has_mean_std_and_paired_ci(records):
    root, psnr = records
    md = campaign_markdown(root)
    means = rows(md, "scene | views | method | n")
    fm = means[("fern", "3", "fm")]
    assert fm[3:5] == ["3", "0, 1, 2"]
    assert fm[5] == f"{np.mean(psnr['fm']):.2f} ± {np.std(psnr['fm'], ddof=1):.2f}"
    assert fm[7] == "0.230 ± 0.000"
    assert fm[8] == "`fern_v3_fm_s0`, `fern_v3_fm_s1`, `fern_v3_fm_s2`"
    diffs = rows(md, "scene | views | difference")
    row = diffs[("fern", "3", "FM − 3DGS")]
    d = np.subtract(psnr["fm"], psnr["3dgs"])
    text, p = ci_text(d, 2)
    assert row[3] == "3" and row[4] == text and row[5] == f"{p:.3f}"
    assert row[6] == str(runs_needed(d.mean(), d.std(ddof=1)))
    d_ssim = np.subtract([0.70, 0.71, 0.72], [0.62, 0.64, 0.66])
    assert row[7] == ci_text(d_ssim, 3)[0]
    # identical LPIPS differences: no spread, no interval
    assert row[10].startswith("-0.040 (zero spread")


def test_one_seed_cell_has_no_interval_and_says_what_is_missing(records):
    root, _ = records
    md = campaign_markdown(root)
    means = rows(md, "scene | views | method | n")
    desk = means[("desk", "3", "fm")]
    assert desk[3:6] == ["1", "0", "18.00"]
    assert desk[8] == f"`desk_v3_fm_s0`; seeds 1, 2: {MISSING}"
    assert means[("desk", "3", "3dgs")][3:6] == ["0", "", MISSING]
    assert means[("cup", "12", "fm")][5] == MISSING
    diffs = rows(md, "scene | views | difference")
    one = diffs[("desk", "3", "FM − DropGaussian")]
    assert one[3] == "1" and one[4] == "+0.50 (n = 1: no interval)" and one[5:7] == ["-", "-"]
    assert diffs[("desk", "3", "FM − 3DGS")][3:5] == ["0", NO_PAIRS]
    assert diffs[("bonsai", "12", "FM − 3DGS")][3:5] == ["0", NO_PAIRS]


def test_pooled_row_takes_every_scene_seed_pair(records):
    root, psnr = records
    diffs = rows(campaign_markdown(root), "scene | views | difference")
    pooled = diffs[("pooled", "3, 12", "FM − DropGaussian")]
    d = list(np.subtract(psnr["fm"], psnr["dropgaussian"])) + [18.0 - 17.5]
    text, p = ci_text(d, 2)
    assert pooled[3] == "4 (fern 3, desk 1)"
    assert pooled[4] == text and pooled[5] == f"{p:.3f}"
    assert diffs[("pooled", "3, 12", "FM − 3DGS")][3] == "3 (fern 3)"


def test_only_records_of_the_grid_count(tmp_path):
    write_record(tmp_path, method="fm")
    other = ["refgs", "run-one", "/r/experiments/other.toml", "--out", "o", "--name", "x"]
    write_record(tmp_path, method="3dgs", command=other)
    write_record(tmp_path, method="dropgaussian", command=["refgs", "train", "--scene", "s"])
    assert [r.record for r in load_campaign(tmp_path)] == ["fern_v3_fm_s0"]
    assert made_by({"command": GRID_COMMAND + ["n"]}, MAIN)
    assert not made_by({"command": None}, MAIN) and not made_by({}, MAIN)
    # the summary families keep the others and leave the campaign's record to its own block
    md = summary_markdown(tmp_path, reports=[MAIN])
    assert "fern_v3_3dgs_s0" in md and "fern_v3_dropgaussian_s0" in md
    assert "fern_v3_fm_s0" not in md


def test_grid_records_outside_the_campaign_are_refused(tmp_path):
    write_record(tmp_path, views=6)
    with pytest.raises(ConfigError, match=r"fern_v6_fm_s0/config\.json: made by .* not a cell"):
        campaign_markdown(tmp_path)
    shutil.rmtree(tmp_path / "fern_v6_fm_s0")
    write_record(tmp_path, iters=3000)
    with pytest.raises(ConfigError, match="'iters': 3000"):
        campaign_markdown(tmp_path)
    s = json.loads((tmp_path / "fern_v3_fm_s0" / "config.json").read_text())
    s["settings"]["iters"] = 10000
    (tmp_path / "fern_v3_fm_s0" / "config.json").write_text(json.dumps(s))
    (tmp_path / "again").mkdir()
    (tmp_path / "again" / "config.json").write_text(json.dumps(s))
    (tmp_path / "again" / "metrics.json").write_text("{}")
    with pytest.raises(ConfigError, match="same scene, views, method and seed as"):
        campaign_markdown(tmp_path)
    with pytest.raises(ConfigError, match="not a folder"):
        campaign_markdown(tmp_path / "nowhere")
    write_record(tmp_path / "other")
    (tmp_path / "other" / "fern_v3_fm_s0" / "metrics.json").write_text('{"psnr": "high"}')
    with pytest.raises(ConfigError, match=r"fern_v3_fm_s0/metrics\.json: psnr = 'high'"):
        campaign_markdown(tmp_path / "other")


def test_update_rewrites_both_blocks(records, capsys):
    root, _ = records
    doc = root.parent / "doc.md"
    begin, end = markers(MAIN)
    doc.write_text(f"# T\n\n{begin}\nold\n{end}\n\nmid\n\n{SUMMARY_MARKERS[0]}\nold\n"
                   f"{SUMMARY_MARKERS[1]}\n")
    grid = str(MAIN.grid)
    assert refgs_main(["report", grid, "--records", str(root), "--update", str(doc)]) == 0
    text = doc.read_text()
    block = split_document(text, "doc", begin, end)[1].strip()
    assert block == campaign_markdown(root).strip()
    assert "### Flatness over training seeds" in block and "### Beside the paper" in block
    summary = split_document(text, "doc", *SUMMARY_MARKERS)[1].strip()
    assert summary == summary_markdown(root, reports=reports_beside([grid])).strip()
    assert refgs_main(["report", grid, "--records", str(root)]) == 0
    assert capsys.readouterr().out == campaign_markdown(root)


def test_compute_segments_follow_the_resumes_and_the_wall_time_counts_overlaps_once(tmp_path):
    """A resumed run is one segment per start, each as long as its iterations' seconds; the wall
    time is the union of every run's segments (refgs.analysis.cost)."""
    config = {"started": "2026-12-05T10:00:00+0000",
              "resumes": [{"from_iteration": 3, "time": "2026-12-05T12:00:00+0000"}]}
    segs = segments(config, {"iter_seconds": [10.0, 20.0, 30.0, 5.0, 5.0]}, "run")
    assert [(a.strftime("%H:%M:%S"), b.strftime("%H:%M:%S")) for a, b in segs] == [
        ("10:00:00", "10:01:00"), ("12:00:00", "12:00:10")]
    # two runs side by side count once; a gap between sessions not at all
    other = segments({"started": "2026-12-05T10:00:30+0000"}, {"iter_seconds": [60.0]}, "b")
    assert union_seconds(segs + other) == 90 + 10
    with pytest.raises(ConfigError, match="run/config.json started"):
        segments({"started": "yesterday"}, {"iter_seconds": [1.0]}, "run")
    with pytest.raises(ConfigError, match="run/history.json: no iter_seconds"):
        segments(config, {}, "run")


def test_compute_table_sums_the_loops(records):
    root, _ = records
    md = cost_markdown(root, load_campaign(root), MAIN.groups, MAIN.methods, MAIN.cost_note)
    cells = rows(md, "scene")
    assert cells[("fern", "3", "fm")][3:5] == ["3", "1.0; 1.0-1.0"]
    # 11 runs of 1 minute, all started at the same time: 11 minutes of compute, 1 of wall time
    assert "11 runs; their training loops add up to 0.2 h of compute" in " ".join(md.split())
    assert "is 0.0 h, between 2026-12-05 10:00 and 2026-12-05 10:01 UTC" in " ".join(md.split())


# --- the qualitative figure -----------------------------------------------------------------
H, W = 96, 128


def fake_run(root: Path, name: str, method: str, seed: int, image: np.ndarray,
             scene="fern", views=3) -> Path:
    d = root / name
    (d / "renders" / "test").mkdir(parents=True)
    settings = {"scene": f"/data/{scene}", "views": views, "seed": seed, "method": method,
                "method_params": {}}
    (d / "config.json").write_text(json.dumps({"settings": settings,
                                               "test_images": ["a.png", "b.JPG"]}))
    for view in ("a", "b"):
        Image.fromarray((np.clip(image, 0, 1) * 255).round().astype(np.uint8)).save(
            d / "renders" / "test" / f"{view}.png")
    return d


@pytest.fixture()
def compare_runs(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    base = rng.random((H, W, 3))
    runs = []
    for k, method in enumerate(("fm", "3dgs", "dropgaussian")):
        img = base.copy()
        img[70:80, 100:110] = rng.random((10, 10, 3))          # where the methods differ
        runs.append(fake_run(tmp_path, f"fern_v3_{method}_s0", method, 0, img))
    runs.append(fake_run(tmp_path, "fern_v3_fm_s1", "fm", 1, base))
    runs.append(fake_run(tmp_path, "cup_v12_fm_s0", "fm", 0, base, scene="cup", views=12))
    monkeypatch.setattr(qualitative, "ground_truth", lambda settings, name, cache: base)
    return tmp_path, runs, base


def test_crop_is_where_the_renders_differ(compare_runs):
    _, _, base = compare_runs
    rng = np.random.default_rng(1)
    imgs = [base.copy() for _ in range(3)]
    for img in imgs:
        img[70:80, 100:110] = rng.random((10, 10, 3))
    y0, x0, h, w = qualitative.crop_window(imgs, base, size=16)
    assert (h, w) == (16, 16) and y0 <= 70 and y0 + h >= 80 and x0 <= 100 and x0 + w >= 110
    # one render: its largest error; a window larger than the image is clipped to it
    err = base.copy()
    err[5:9, 3:7] = 1 - err[5:9, 3:7]
    y0, x0, h, w = qualitative.crop_window([err], base, size=8)
    assert y0 <= 5 and y0 + h >= 9 and x0 <= 3 and x0 + w >= 7
    assert qualitative.crop_window([err], base, size=1000) == (0, 0, H, W)


def test_compare_figures_group_by_scene_and_seed(compare_runs, capsys):
    root, runs, _ = compare_runs
    out = root / "figs"
    written = make_figures(runs, out=out, compare=True)
    assert [p.name for p in written] == ["compare_cup_v12_s0.png", "compare_fern_v3_s0.png",
                                         "index.md"]
    with Image.open(out / "compare_fern_v3_s0.png") as im:
        assert im.size[0] > 4 * 200 and np.asarray(im.convert("L")).std() > 1
    index = (out / "index.md").read_text()
    assert "ground truth | 3dgs | dropgaussian | fm" in index and "test view a.png" in index
    groups = qualitative.plan(runs, seed=1, view=1)
    assert list(groups) == [("fern", 3)] and [r.label for r in groups[("fern", 3)]] == ["fm"]
    assert qualitative.main([str(r) for r in runs] + ["--seed", "1", "--out", str(root / "q")]) == 0
    assert (root / "q" / "compare_fern_v3_s1.png").is_file()


def test_compare_refuses_before_writing(compare_runs, capsys):
    root, runs, _ = compare_runs
    (runs[0] / "renders" / "test" / "a.png").unlink()
    with pytest.raises(ConfigError, match=r"a\.png: not found \(render it with: refgs render"):
        make_figures(runs, out=root / "o", compare=True)
    with pytest.raises(ConfigError, match="--view 2:"):
        qualitative.plan(runs[1:], view=2)
    with pytest.raises(ConfigError, match="--seed 5: none of the"):
        qualitative.plan(runs, seed=5)
    assert not (root / "o").exists()
    assert qualitative.main([str(root / "nope")]) == 2
    assert "config.json" in capsys.readouterr().err


# --- flatness over seeds ----------------------------------------------------------------------
def curve(test_means, train_means, run=None, gammas=(0.0, 0.5, 1.0)) -> dict:
    c = {"gammas": list(gammas), "settings": "flatness", "p": 1.0, "alpha": 1.0, "clamp": "none",
         "test": {"mean": list(test_means), "std": [0.0] * len(gammas), "all": []},
         "train": {"mean": list(train_means), "std": [0.0] * len(gammas), "all": []}}
    if run is not None:
        c["run"] = run
    return c


def test_flatness_over_seeds_mean_and_t_band(tmp_path):
    test = {0: [20.0, 19.0, 18.0], 1: [21.0, 20.5, 19.0], 2: [20.5, 19.5, 17.5]}
    curves = {}
    for seed, t in test.items():
        info = {"name": f"fern_v3_fm_s{seed}", "scene": "fern", "views": 3, "label": "fm",
                "seed": seed}
        curves[f"fern_v3_fm_s{seed} (fm, t=10000)"] = curve(t, [30.0, 26.0, 24.0 + seed], info)
    curves["fern_v3_3dgs_s0 (3dgs, t=10000)"] = curve(
        [19.0, 15.0, 12.0], [35.0, 20.0, 18.0],
        {"name": "fern_v3_3dgs_s0", "scene": "fern", "views": 3, "label": "3dgs", "seed": 0})
    groups = group_over_seeds(curves)
    fm, base = groups["fern, 3 views"]["fm"], groups["fern, 3 views"]["3dgs"]
    a = np.asarray(list(test.values()))
    half = stats.t.ppf(0.975, 2) * a.std(axis=0, ddof=1) / np.sqrt(3)
    assert fm["n"] == 3 and fm["test"]["mean"] == pytest.approx(a.mean(axis=0).tolist())
    assert fm["test"]["lo"] == pytest.approx((a.mean(axis=0) - half).tolist())
    assert fm["test"]["hi"] == pytest.approx((a.mean(axis=0) + half).tolist())
    assert fm["train"]["lo"][0] == pytest.approx(30.0)                   # no spread at gamma 0
    assert base["n"] == 1 and base["test"]["lo"] is None and base["test"]["hi"] is None
    path = tmp_path / "f.json"
    path.write_text(json.dumps({"runs": curves}))
    written = make_figures([], flatness=[path], out=tmp_path / "figs", over_seeds=True)
    assert {p.name for p in written} == {"flatness.png", "flatness_over_seeds.png", "index.md"}
    assert "fern, 3 views: 3dgs (n=1), fm (n=3)" in (tmp_path / "figs" / "index.md").read_text()


def test_flatness_over_seeds_without_run_info_and_errors(tmp_path):
    # flatness.json files written before curves carried "run": grouped by run name minus _s<seed>
    assert curve_key("fern3_fm_s2 (fm, t=10000)", {}) == ("", "fern3_fm", "2")
    assert curve_key("odd (fm, t=10)", {}) == ("", "odd", "")
    g = group_over_seeds({"fern3_fm_s0 (fm)": curve([1, 2, 3], [4, 5, 6]),
                          "fern3_fm_s2 (fm)": curve([3, 4, 5], [4, 5, 6])})
    assert g[""]["fern3_fm"]["n"] == 2 and g[""]["fern3_fm"]["test"]["mean"] == [2, 3, 4]
    with pytest.raises(ConfigError, match="different gammas"):
        group_over_seeds({"a_s0": curve([1, 2], [1, 2], gammas=(0, 1)),
                          "a_s1": curve([1, 2, 3], [1, 2, 3])})
    with pytest.raises(ConfigError, match="the same run"):
        group_over_seeds({"a_s0 (x)": curve([1, 2, 3], [1, 2, 3]),
                          "a_s0 (x) (other.json)": curve([1, 2, 3], [1, 2, 3])})
    with pytest.raises(ConfigError, match="--over-seeds: give the flatness.json"):
        make_figures([tmp_path], out=tmp_path / "o", over_seeds=True)


# --- the flatness over training seeds (refgs.analysis.flatness_drops) -------------------------
def write_flatness(root: Path, name: str, curves: dict, settings="flatness") -> Path:
    """A flatness record: curves {campaign run name: (test means, train means)} over gamma 0, 1."""
    folder = root / name
    folder.mkdir(parents=True)
    runs = {}
    for run, (test, train) in curves.items():
        scene, views, method, seed = run.split("_")
        runs[f"{run} ({method}, t=10000)"] = {
            "gammas": [0.0, 1.0], "settings": settings, "run": {
                "name": run, "scene": scene, "views": int(views[1:]), "label": method,
                "seed": int(seed[1:])},
            "test": {"mean": test, "std": [0.0, 0.1], "all": [[test[0]], [test[1]]]},
            "train": {"mean": train, "std": [0.0, 0.1], "all": [[train[0]], [train[1]]]}}
    (folder / "flatness.json").write_text(json.dumps({"runs": runs}))
    return folder


def test_flatness_table_means_drops_and_paired_difference(records):
    root, _ = records
    fm_drop, base_drop = [0.3, 0.5, 0.2], [1.5, 2.0, 1.9]
    curves = {}
    for s in range(3):
        curves[f"fern_v3_fm_s{s}"] = ([21.0, 21.0 - fm_drop[s]], [30.0, 26.0])
        curves[f"fern_v3_3dgs_s{s}"] = ([19.0, 19.0 - base_drop[s]], [35.0, 20.0])
    curves["desk_v3_fm_s0"] = ([18.0, 17.0], [30.0, 25.0])       # not in FLATNESS_SCENES
    write_flatness(root, "flat_a", {k: v for k, v in curves.items() if k.endswith("s0")})
    write_flatness(root, "flat_b", {k: v for k, v in curves.items() if not k.endswith("s0")})
    write_flatness(root, "flat_training", {"fern_v3_dropgaussian_s0": ([20.0, 19.0], [30.0, 29.0])},
                   settings="training")                            # other settings: left out
    md = flatness_markdown(root, MAIN, load_campaign(root))
    means = rows(md, "scene | views | method | n | test")
    fm = means[("fern", "3", "fm")]
    assert fm[3] == "3" and fm[4] == "21.00"
    assert fm[5] == f"{np.mean([21.0 - d for d in fm_drop]):.2f} (γ = 1)"
    assert fm[6] == ci_text(fm_drop, 2)[0]
    assert fm[-1] == "`flat_a`, `flat_b`"
    assert means[("fern", "3", "dropgaussian")][3:5] == ["0", "not analysed yet"]
    diffs = rows(md, "scene | views | difference")
    d = diffs[("fern", "3", "FM − 3DGS")]
    text, p = ci_text(np.subtract(fm_drop, base_drop), 2)
    assert d[3] == "3" and d[4] == text and d[5] == f"{p:.3f}"
    assert diffs[("fern", "3", "FM − DropGaussian")][3:5] == ["0", "no pairs yet"]


def test_flatness_table_refuses_two_curves_of_one_run(records):
    root, _ = records
    write_flatness(root, "flat_a", {"fern_v3_fm_s0": ([21.0, 20.0], [30.0, 26.0])})
    write_flatness(root, "flat_b", {"fern_v3_fm_s0": ([21.0, 20.5], [30.0, 26.0])})
    with pytest.raises(ConfigError, match="fern_v3_fm_s0 also has a curve in flat_a"):
        flatness_markdown(root, MAIN, load_campaign(root))


def test_paper_table_sets_our_means_beside_the_papers(records):
    root, psnr = records
    md = paper_table(MAIN, load_campaign(root))
    fern = rows(md, "scene | paper's mean over")
    row = fern[("fern 3-view", "LLFF 3-view, mean of 8 scenes", "PSNR")]
    paper = MAIN.quotes[0].values
    assert row[3] == "3/3/3"
    assert row[6] == f"{np.mean(psnr['fm']):.2f} / {paper['fm'][0]:.2f}"
    assert row[7] == f"{np.mean(psnr['fm']) - np.mean(psnr['3dgs']):+.2f} / " \
                     f"{paper['fm'][0] - paper['3dgs'][0]:+.2f}"
    bonsai = fern[("bonsai 12-view", "Mip-NeRF 360 12-view, mean of 9 scenes", "LPIPS-VGG")]
    assert bonsai[3] == "0/0/0" and bonsai[4] == f"- / {MAIN.quotes[1].values['3dgs'][2]:.3f}"


def test_runs_of_the_campaign_code_outside_the_grid_have_their_own_family(tmp_path):
    root = tmp_path / "records"
    older = write_record(root, method="3dgs", seed=2, psnr=19.3, command=["refgs", "train"],
                         dtype="float64")
    ours = write_record(root, method="3dgs", seed=0, psnr=19.55, command=["refgs", "train"],
                        dtype="float64")
    ours = ours.rename(root / "fern_v3_3dgs_f64_s0")
    cfg = json.loads((ours / "config.json").read_text())
    cfg["provenance"] = {"source_hash": CODE}
    (ours / "config.json").write_text(json.dumps(cfg))
    md = summary_markdown(root, reports=[MAIN])
    own = md.split("### Made by the campaign's code, outside its grid", 1)[1].split("###", 1)[0]
    assert "| fern | 3 | 3dgs, float64 | 0 | 19.55 |" in own and older.name not in own
    fern = md.split("### Fern, 3 views", 1)[1]
    assert f"`{older.name}`" in fern and "fern_v3_3dgs_f64_s0" not in fern


# --- the follow-ups: ablations and more views (experiments/paper_followups.toml) -----------------
FOLLOWUP_COMMAND = ["refgs", "run-one", "/elsewhere/repo/experiments/paper_followups.toml", "--out",
                    "/elsewhere/repo/runs/paper_followups", "--name"]


def write_followup(root: Path, name: str, source_hash=None, **kw) -> Path:
    """A follow-up record named ``name``, made by the campaign's code unless ``source_hash``."""
    tmp = write_record(root / ".new", command=FOLLOWUP_COMMAND + [name], **kw)
    folder = tmp.rename(root / name)
    tmp.parent.rmdir()
    cfg = json.loads((folder / "config.json").read_text())
    cfg["provenance"] = {"source_hash": source_hash or FOLLOWUPS.code[0]}
    (folder / "config.json").write_text(json.dumps(cfg))
    return folder


def test_followups_pair_ablations_with_the_campaigns_fm_and_views_by_seed(records, capsys):
    root, psnr = records
    noreinit = [20.5, 20.9, 20.2]
    for seed in range(3):
        write_followup(root, f"fern_v3_fm_fm-no-reinit_s{seed}", seed=seed, psnr=noreinit[seed],
                       method_params={"reinit": False})
    v6 = {"fm": [24.0, 24.5], "3dgs": [23.0, 23.9]}
    for m, vals in v6.items():
        for seed, v in enumerate(vals):
            write_followup(root, f"fern_v6_{m}_s{seed}", views=6, method=m, seed=seed, psnr=v)
    md = followups_markdown(root)
    means = rows(md, "method | views | n")
    assert means[("FM w/o reinitialisation", "3", "3")][4] == mean_sd(noreinit)
    assert means[("FM (main campaign)", "3", "3")][4] == mean_sd(psnr["fm"])
    assert means[("FM w/o scheduling", "3", "0")][4] == MISSING
    ablations, views = md.split("*Views, fern*")
    means = rows(views, "method | views | n")
    assert means[("DropGaussian", "6", "0")][4] == MISSING
    assert "seed 2: " + MISSING in means[("FM", "6", "2")][-1]
    diffs = {**rows(ablations, "scene | views | difference"),
             **rows(views, "scene | views | difference")}
    got = diffs[("fern", "3", "FM w/o reinitialisation − FM")]
    want, p = ci_text([a - b for a, b in zip(noreinit, psnr["fm"])], 2)
    assert got[3] == "3" and got[4] == want and got[5] == f"{p:.3f}"
    assert diffs[("fern", "3", "FM w/o scheduling − FM")][4] == NO_PAIRS
    want6, _ = ci_text([a - b for a, b in zip(v6["fm"], v6["3dgs"])], 2)
    assert diffs[("fern", "6", "FM − 3DGS")][4] == want6
    fm3, _ = ci_text([a - b for a, b in zip(psnr["fm"], psnr["3dgs"])], 2)
    assert diffs[("fern", "3", "FM − 3DGS")][4] == fm3          # the main campaign's records
    # the summary families leave them to this block; the command prints it
    assert "fern_v6_fm_s0" not in summary_markdown(root, reports=[MAIN, FOLLOWUPS])
    grid = str(FOLLOWUPS.grid)
    assert refgs_main(["report", grid, "--records", str(root)]) == 0
    assert capsys.readouterr().out == md


def mean_sd(values):
    a = np.asarray(values)
    return f"{a.mean():.2f} ± {a.std(ddof=1):.2f}"


def test_followups_refuse_other_cells_and_other_code(tmp_path):
    write_followup(tmp_path, "fern_v3_3dgs_s0", method="3dgs")     # 3 views: ablations only
    with pytest.raises(ConfigError, match=r"fern_v3_3dgs_s0/config\.json: made by "
                                          r"experiments/paper_followups\.toml .* not a cell"):
        followups_markdown(tmp_path)
    shutil.rmtree(tmp_path / "fern_v3_3dgs_s0")
    write_followup(tmp_path, "fern_v9_fm_s0", views=9, source_hash="0000000000000000")
    with pytest.raises(ConfigError, match="source hash 0000000000000000 is not one the grid"):
        followups_markdown(tmp_path)
    shutil.rmtree(tmp_path / "fern_v9_fm_s0")
    write_followup(tmp_path, "a", views=9)
    write_followup(tmp_path, "b", views=9)
    with pytest.raises(ConfigError, match="b: same scene, views, method and seed as a"):
        followups_markdown(tmp_path)


def test_update_rewrites_the_followups_block(records):
    root, _ = records
    write_followup(root, "fern_v9_fm_s0", views=9, psnr=26.0)
    doc = root.parent / "doc.md"
    begin, end = markers(FOLLOWUPS)
    doc.write_text(f"# t\n{SUMMARY_MARKERS[0]}\nold\n{SUMMARY_MARKERS[1]}\n{begin}\nstale\n"
                   f"{end}\nend\n")
    assert refgs_main(["report", str(FOLLOWUPS.grid), "--records", str(root), "--update",
                       str(doc)]) == 0
    text = doc.read_text()
    assert split_document(text, "doc", begin, end)[1].strip() == followups_markdown(root).strip()
    assert "stale" not in text and text.endswith("end\n")
