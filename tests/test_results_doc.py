"""docs/results.md's blocks are exactly what the builders make from the committed records (FM-15):
each reported grid's block (refgs.analysis.report, every experiments/*.toml with a [report]
table) and the summary of the other records (refgs.analysis.summary); the summary builder
computes, marks and refuses what it should (the grids' blocks on made-up records:
test_campaign_analysis.py, test_report.py)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from refgs.analysis.report import (SUMMARY_MARKERS, markers, report_markdown, reports_beside,
                                   split_document, with_block)
from refgs.analysis.report_spec import load_report
from refgs.analysis.summary import default_unrecorded, load_records, summary_markdown
from refgs.cli import main as refgs_main
from refgs.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "results" / "records"
DOC = ROOT / "docs" / "results.md"
GRIDS = sorted((ROOT / "experiments").glob("*.toml"))
REPORTS = reports_beside(GRIDS)
UPDATE = ("refgs report " + " ".join(f"experiments/{r.grid.name}" for r in REPORTS)
          + " --records results/records --update docs/results.md")


def test_results_doc_summary_is_generated_from_the_records():
    _, block, _ = split_document(DOC.read_text(encoding="utf-8"), str(DOC), *SUMMARY_MARKERS)
    expected = summary_markdown(RECORDS, default_unrecorded(RECORDS), REPORTS)
    assert block.strip() == expected.strip(), f"docs/results.md is out of date; run: {UPDATE}"


def test_the_experiments_with_a_report():
    assert {r.marker for r in REPORTS} >= {"main", "followups"}


@pytest.mark.parametrize("report", REPORTS, ids=lambda r: r.grid.name)
def test_results_doc_block_of_every_reported_grid_is_generated_from_the_records(report):
    text = DOC.read_text(encoding="utf-8")
    _, block, _ = split_document(text, str(DOC), *markers(report))
    assert block.strip() == report_markdown(report, RECORDS).strip(), \
        f"docs/results.md is out of date; run: {UPDATE}"
    # the grids' blocks come before the summary
    assert text.index(markers(report)[1]) < text.index(SUMMARY_MARKERS[0])


def test_results_doc_block_order():
    text = DOC.read_text(encoding="utf-8")
    assert text.index("<!-- main:end -->") < text.index("<!-- followups:begin -->")


def test_every_record_is_in_the_results_doc():
    text = DOC.read_text(encoding="utf-8")
    missing = [p.name for p in sorted(RECORDS.iterdir()) if p.is_dir() and f"`{p.name}`" not in text]
    assert not missing, f"records not in docs/results.md: {missing}"


def test_the_run_log_is_linked():
    assert "(runlog.md)" in DOC.read_text(encoding="utf-8")
    assert (ROOT / "docs" / "runlog.md").is_file()


# --- the builder on made-up records ---------------------------------------------------------
def write_run(root: Path, name: str, scene="fern", views=3, iters=10000, seed=0, method="fm",
              params=None, psnr=20.0, ssim=0.7, lpips=0.2) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    settings = {"scene": f"/data/{scene}", "views": views, "iters": iters, "seed": seed,
                "method": method, "method_params": params or {}}
    (folder / "config.json").write_text(json.dumps({"settings": settings}))
    (folder / "metrics.json").write_text(json.dumps({"psnr": psnr, "ssim": ssim, "lpips_vgg": lpips}))
    return folder


def table_rows(md: str, title: str) -> list[list[str]]:
    """The cells of the body rows of the table under ``### title``."""
    section = md.split(f"### {title}\n", 1)[1].split("\n### ", 1)[0]
    lines = [ln for ln in section.splitlines() if ln.startswith("| ")][1:]
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]


def test_mean_and_sample_std_over_seeds(tmp_path):
    psnrs, ssims = [20.1, 21.3, 20.65], [0.70, 0.72, 0.69]
    for seed, (p, s) in enumerate(zip(psnrs, ssims)):
        write_run(tmp_path, f"fern3_fm_s{seed}", seed=seed, psnr=p, ssim=s, lpips=0.25)
    write_run(tmp_path, "fern3_3dgs_s0", method="3dgs", psnr=19.0)
    rows = table_rows(summary_markdown(tmp_path), "Fern, 3 views: the three methods over seeds")
    assert [r[2] for r in rows] == ["3dgs", "fm"]
    fm = rows[1]
    assert fm[3] == "0, 1, 2"
    assert fm[4] == f"{np.mean(psnrs):.2f} ± {np.std(psnrs, ddof=1):.2f}"
    assert fm[5] == f"{np.mean(ssims):.3f} ± {np.std(ssims, ddof=1):.3f}"
    assert fm[6] == "0.250 ± 0.000"
    assert fm[7] == "`fern3_fm_s0`, `fern3_fm_s1`, `fern3_fm_s2`"
    assert rows[0][4] == "19.00"                 # one seed: the value, no ± 0


def test_families_ablation_deltas_and_unrecorded_rows(tmp_path):
    write_run(tmp_path / "rec", "fern3_fm_s0", psnr=21.0, ssim=0.70, lpips=0.23)
    write_run(tmp_path / "rec", "fern3_fm_rot_s0", params={"perturb": "rotation"}, psnr=20.5,
              ssim=0.69, lpips=0.24)
    write_run(tmp_path / "rec", "fern3_fm_rot_s1", params={"perturb": "rotation"}, seed=1,
              psnr=20.0)
    write_run(tmp_path / "rec", "fern3_dg_fm_s0", method="dropgaussian", params={"fm": True})
    write_run(tmp_path / "rec", "bonsai12_3dgs_s0", scene="bonsai", views=12, method="3dgs")
    write_run(tmp_path / "rec", "room4_fm_s0", scene="room", views=4)
    (tmp_path / "unrecorded.toml").write_text(
        '[[run]]\nscene = "fern"\nviews = 3\niters = 3000\nmethod = "fm"\nseeds = "0"\n'
        'note = "lost"\n')
    assert default_unrecorded(tmp_path / "rec") == tmp_path / "unrecorded.toml"
    md = summary_markdown(tmp_path / "rec", tmp_path / "unrecorded.toml")
    titles = [ln[4:] for ln in md.splitlines() if ln.startswith("### ")]
    assert titles == ["Fern, 3 views: the three methods over seeds", "Bonsai, 12 views",
                      "FM as a plug-in on DropGaussian",
                      "Ablations of FM (difference from the fm record of the same seed)",
                      "Other runs"]
    abl = table_rows(md, titles[3])
    assert len(abl) == 1 and abl[0][2] == "fm[perturb=rotation]" and abl[0][3] == "0, 1"
    # seed 1 has no fm record to pair with: no difference is made up
    assert abl[0][7:10] == ["n/a"] * 3 and abl[0][10] == "no fm record of seed(s) 1"
    assert table_rows(md, titles[2])[0][2] == "dropgaussian+fm"
    other = table_rows(md, "Other runs")
    assert [r[0] for r in other] == ["fern", "room"]
    assert other[0][2] == "fm, T = 3000" and other[0][4] == "no record" and other[0][-1] == "lost"


def test_ablation_delta_paired_by_seed(tmp_path):
    write_run(tmp_path, "fern3_fm_s0", psnr=21.0, ssim=0.700, lpips=0.230)
    write_run(tmp_path, "fern3_fm_noreinit_s0", params={"reinit": False}, psnr=20.75, ssim=0.680,
              lpips=0.241)
    rows = table_rows(summary_markdown(tmp_path), "Ablations of FM (difference from the fm "
                                                  "record of the same seed)")
    assert rows[0][2] == "fm[reinit=False]"
    assert rows[0][7:11] == ["-0.25", "-0.020", "+0.011", "`fern3_fm_s0`"]


def test_flatness_records_are_tabulated(tmp_path):
    write_run(tmp_path, "fern3_fm_s0")
    folder = tmp_path / "flatness_x"
    folder.mkdir()
    curve = {"gammas": [0.0, 0.5, 1.0], "p": 1.0, "alpha": 1.0, "clamp": "none",
             "test": {"mean": [20.0, 18.5, 19.0], "std": [0.0, 0.3, 0.2],
                      "all": [[20.0] * 3, [18.5] * 3, [19.0] * 3]},
             "train": {"mean": [30.0, 28.0, 26.0], "std": [0.0, 0.1, 0.05],
                       "all": [[30.0] * 3, [28.0] * 3, [26.0] * 3]}}
    (folder / "flatness.json").write_text(json.dumps({"runs": {"fern3_fm_s0 (fm, t=10000)": curve}}))
    runs, flatness = load_records(tmp_path)
    assert [r.record for r in runs] == ["fern3_fm_s0"] and list(flatness) == ["flatness_x"]
    row = table_rows(summary_markdown(tmp_path), "Flatness of the final models (SAP at p = 1, "
                                                 "α = 1, no clamp)")[0]
    assert row == ["fern3_fm_s0", "3", "20.00", "19.00 ± 0.20 (γ = 1)", "1.50 (γ = 0.5)",
                   "30.00", "26.00 ± 0.05 (γ = 1)", "4.00 (γ = 1)", "`flatness_x`"]


def test_bad_records_name_the_file(tmp_path):
    folder = write_run(tmp_path, "fern3_fm_s0")
    (folder / "metrics.json").write_text("{not json")
    with pytest.raises(ConfigError, match=r"fern3_fm_s0/metrics\.json: not valid JSON"):
        summary_markdown(tmp_path)
    (folder / "metrics.json").unlink()
    with pytest.raises(ConfigError, match=r"fern3_fm_s0/metrics\.json: not found"):
        summary_markdown(tmp_path)
    (folder / "config.json").unlink()
    with pytest.raises(ConfigError, match="fern3_fm_s0: neither config.json nor flatness.json"):
        summary_markdown(tmp_path)
    with pytest.raises(ConfigError, match="not a folder"):
        summary_markdown(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    (tmp_path / "u.toml").write_text('[[run]]\nscene = "fern"\n')
    with pytest.raises(ConfigError, match=r"u\.toml: run 1: expected scene, views"):
        summary_markdown(tmp_path / "empty", tmp_path / "u.toml")
    (tmp_path / "u.toml").write_text("[[run]\n")
    with pytest.raises(ConfigError, match=r"u\.toml: not a readable TOML file"):
        summary_markdown(tmp_path / "empty", tmp_path / "u.toml")


def test_markers_and_update(tmp_path, capsys):
    write_run(tmp_path / "rec", "fern3_fm_s0")
    doc = tmp_path / "doc.md"
    begin, end = SUMMARY_MARKERS
    doc.write_text(f"# T\n\nintro\n\n{begin}\nold table\n{end}\n\noutro\n")
    grid = tmp_path / "g.toml"
    grid.write_text('scene = "s"\nviews = 3\niters = 10\n\n[report]\ntitle = "G"\n')
    doc.write_text(doc.read_text() + "<!-- g:begin -->\n<!-- g:end -->\n")
    assert refgs_main(["report", str(grid), "--records", str(tmp_path / "rec"), "--update",
                       str(doc)]) == 0
    text = doc.read_text()
    assert "old table" not in text and text.startswith("# T\n\nintro\n\n")
    assert text.endswith("outro\n<!-- g:begin -->\n\n" + report_markdown(
        load_report(grid), tmp_path / "rec").strip() + "\n\n<!-- g:end -->\n")
    _, block, _ = split_document(text, "doc", begin, end)
    assert block.strip() == summary_markdown(tmp_path / "rec").strip()
    assert with_block(text, summary_markdown(tmp_path / "rec"), "doc", begin, end) == text
    doc.write_text("no markers\n")
    assert refgs_main(["report", str(grid), "--records", str(tmp_path / "rec"), "--update",
                       str(doc)]) == 2
    assert "expected one <!-- g:begin -->" in capsys.readouterr().err
    assert doc.read_text() == "no markers\n"
    with pytest.raises(ConfigError, match="comes before"):
        split_document(f"{end}\n{begin}\n", "doc", begin, end)
