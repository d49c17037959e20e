"""A grid of one's own with a [report] table gets its report from ``refgs report``
(refgs.analysis.report, report_spec), bad [report] tables are refused with one line naming the
key, and new training code is accepted only when it reproduces the pinned run bit for bit
(refgs.analysis.equivalence)."""
from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from refgs.analysis import equivalence
from refgs.train.checkpoint import float_environment_key
from refgs.analysis.report import load_runs, markers, report_markdown, split_document
from refgs.analysis.report_spec import load_report
from refgs.cli import main as refgs_main
from refgs.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
FERN = ROOT.parent / "shared" / "data" / "fern"
CODE = "c0de000000000001"

GRID = f"""scene = ["../data/garden", "../data/room"]
views = 4
iters = 500
backend = "reference"
seed = [0, 1, 2]

[[group]]
method = "3dgs"

[[group]]
method = "fm"
fm_gamma = 1.5

[report]
title = "My study: FM on two rooms"
intro = "The grid `{{grid}}`: {{scenes}}; seeds {{seeds}}; {{settings}}."
names = {{ "3dgs" = "3DGS", "fm[gamma=1.5]" = "FM (γ = 1.5)" }}
comparisons = [["fm[gamma=1.5]", "3dgs"]]
pooled = true
metrics = [{{ key = "psnr", title = "PSNR", decimals = 2 }}, {{ key = "ssim", title = "SSIM", decimals = 3 }}]

[[report.quote]]
source = "Table 9: a made-up table"
over = "garden 4-view"
scene = "garden"
views = 4
values = {{ "3dgs" = [20.0, 0.600], "fm[gamma=1.5]" = [21.0, 0.650] }}

[report.paper]
note = "The quoted numbers are made up."

[[report.code]]
hash = "{CODE}"
how = "the code this test says made the runs"
"""


def write_record(records: Path, grid: Path, scene: str, method: str, seed: int, psnr: float,
                 ssim: float, code: str = CODE) -> Path:
    label = "fm" if method.startswith("fm") else method
    name = f"{scene}_v4_{label}_s{seed}"
    folder = records / name
    folder.mkdir(parents=True)
    settings = {"scene": f"/somewhere/{scene}", "views": 4, "iters": 500, "seed": seed,
                "method": label, "method_params": {"gamma": 1.5} if label == "fm" else {},
                "backend": "reference"}
    config = {"command": ["refgs", "run-one", str(grid), "--out", "o", "--name", name],
              "settings": settings, "provenance": {"source_hash": code}}
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "metrics.json").write_text(json.dumps({"psnr": psnr, "ssim": ssim}))
    return folder


@pytest.fixture()
def study(tmp_path):
    grid = tmp_path / "experiments" / "my_study.toml"
    grid.parent.mkdir()
    grid.write_text(GRID)
    records = tmp_path / "records"
    psnr = {"3dgs": [19.0, 19.4, 19.1], "fm[gamma=1.5]": [20.0, 20.1, 20.5]}
    for method, values in psnr.items():
        for seed, p in enumerate(values):
            write_record(records, grid, "garden", method, seed, p, 0.6 + 0.01 * seed)
    write_record(records, grid, "room", "fm[gamma=1.5]", 0, 25.0, 0.8)
    return grid, records, psnr


def table(md: str, first: str) -> dict:
    block = md.split(f"| {first}", 1)[1].split("\n\n", 1)[0]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in block.splitlines()[2:]]
    return {tuple(c[:3]): c for c in cells}


def test_a_grid_of_ones_own_gets_its_report_from_refgs_report(study, capsys):
    grid, records, psnr = study
    doc = grid.parent.parent / "notes.md"
    doc.write_text("# Notes\n\n<!-- my_study:begin -->\nold\n<!-- my_study:end -->\n\nend\n")
    assert refgs_main(["report", str(grid), "--records", str(records), "--update", str(doc)]) == 0
    block = split_document(doc.read_text(), "notes", *markers(load_report(grid)))[1]
    assert refgs_main(["report", str(grid), "--records", str(records)]) == 0
    md = capsys.readouterr().out
    assert block.strip() == md.strip() and doc.read_text().endswith("\n\nend\n")
    assert " ".join(md.split()).startswith(
        "## My study: FM on two rooms The grid `experiments/my_study.toml`: garden (4 views), "
        "room (4 views); seeds 0, 1, 2; 500 iterations, `images_8`, the reference backend.")
    means = table(md, "scene | views | method | n")
    fm = means[("garden", "4", "fm[gamma=1.5]")]
    a = np.asarray(psnr["fm[gamma=1.5]"])
    assert fm[3:6] == ["3", "0, 1, 2", f"{a.mean():.2f} ± {a.std(ddof=1):.2f}"]
    assert means[("room", "4", "3dgs")][3:6] == ["0", "", "running or not yet run"]
    diffs = table(md, "scene | views | difference")
    d = a - np.asarray(psnr["3dgs"])
    ci = stats.ttest_1samp(d, 0.0).confidence_interval(0.95)
    assert diffs[("garden", "4", "FM (γ = 1.5) − 3DGS")][4] == \
        f"**{d.mean():+.2f}** [{ci.low:+.2f}, {ci.high:+.2f}]"
    assert diffs[("pooled", "4", "FM (γ = 1.5) − 3DGS")][3] == "3 (garden 3)"
    assert "negative Δ" not in md and "of the two scenes" in md       # no LPIPS metric here
    paper = table(md, "scene | paper's mean over")
    assert paper[("garden 4-view", "garden 4-view", "PSNR")][4:] == [
        f"{np.mean(psnr['3dgs']):.2f} / 20.00", f"{a.mean():.2f} / 21.00",
        f"{a.mean() - np.mean(psnr['3dgs']):+.2f} / +1.00"]
    assert "LPIPS" not in md and "Flatness" not in md and "cost" not in md


def test_records_of_other_code_or_other_settings_are_refused(study):
    grid, records, _ = study
    report = load_report(grid)
    assert len(load_runs(records, report)) == 7
    bad = write_record(records, grid, "room", "3dgs", 1, 20.0, 0.7, code="0" * 16)
    with pytest.raises(ConfigError, match=r"room_v4_3dgs_s1/config\.json: made by "
                                          r"experiments/my_study\.toml but its source hash 0{16}"):
        load_runs(records, report)
    cfg = json.loads((bad / "config.json").read_text())
    cfg["provenance"]["source_hash"] = CODE
    cfg["settings"]["iters"] = 1000
    (bad / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ConfigError, match=r"seed 1, \{'iters': 1000\} is not a cell of the grid"):
        load_runs(records, report)


@pytest.mark.parametrize("extra, match", [
    ('\n[report.cost]\nnote = 1\n', r"report\.cost\.note: expected str"),
    ('\n[report.flatness]\ngroups = [["fern"]]\n', r"report\.flatness\.groups: expected a list"),
    ('\n[[report.part]]\nlayout = "wide"\n', r"report\.part\[0\]\.layout: expected one of"),
    ('\n[[report.part]]\nrows = 3\n', r"report\.part\[0\]\.rows: unknown key"),
    ('\n[[report.quote]]\nsource = "t"\nover = "o"\nscene = "garden"\nviews = 4\n'
     'values = { fm = [1.0] }\n', r"report\.quote\[1\]\.values\.fm: expected 2 numbers"),
    ('\n[[report.quote]]\nsource = "t"\nover = "o"\nscene = "garden"\nviews = 4\n'
     'values = { "3dgs" = [19.0, 0.6] }\n', "two quotes of garden 4-view 3dgs disagree"),
    ('\n[report.equivalence]\nscene = "x"\nviews = 3\niters = 5\nmethod = ["fm", "3dgs"]\n',
     r"report\.equivalence\.method: expected one value"),
    ('\n[report.equivalence]\nscene = "x"\nviews = 3\niters = 5\nout = "y"\n',
     r"report\.equivalence\.out: not allowed"),
])
def test_bad_report_tables_name_the_key(tmp_path, extra, match):
    grid = tmp_path / "g.toml"
    grid.write_text(GRID + extra)
    with pytest.raises(ConfigError, match=match):
        load_report(grid)


def test_report_table_errors(tmp_path):
    grid = tmp_path / "g.toml"
    grid.write_text(GRID.replace('title = "My study: FM on two rooms"\n', "titel = 1\n"))
    with pytest.raises(ConfigError, match=r"report\.title: required"):
        load_report(grid)
    grid.write_text(GRID.replace("[report]\n", "[report]\ninclude = [\"g.toml\"]\n"))
    with pytest.raises(ConfigError, match="includes itself"):
        load_report(grid)
    grid.write_text(GRID.split("[report]")[0])
    with pytest.raises(ConfigError, match=r"no \[report\] table"):
        load_report(grid)
    grid.write_text(GRID.replace("{settings}", "{setings}"))
    with pytest.raises(ConfigError, match="unknown placeholder 'setings'"):
        report_markdown(load_report(grid), tmp_path)
    assert refgs_main(["report", str(tmp_path / "none.toml")]) == 2


# --- equivalent code ---------------------------------------------------------------------------
PINNED = """
[report.equivalence]
scene = "{fern}"
images = "images_8"
resolution = 8
views = 3
method = "fm"
iters = 20
backend = "fast"
densify_from = 5
densify_interval = 5
eval_every = 0
checkpoint_every = 0
no_lpips = true
"""


def pinned_grid(tmp_path, pins: str = "") -> Path:
    grid = tmp_path / "g.toml"
    grid.write_text(GRID + PINNED.format(fern=FERN) + pins)
    return grid


def test_new_code_is_accepted_only_with_the_pinned_digest(tmp_path, monkeypatch):
    """The check's logic with the pinned run replaced: the reference code pins the digest of
    this float environment, equal code is appended to [[report.code]], different code is refused."""
    level = float_environment_key()
    made = {"reference": ("d" * 64, CODE), "current": ("d" * 64, "new0000000000001")}
    monkeypatch.setattr(equivalence, "run_code", lambda root, argv, out: made[out.name])
    monkeypatch.setattr(equivalence, "source_hash", lambda: "new0000000000001")
    grid = pinned_grid(tmp_path)
    with pytest.raises(ConfigError, match="--reference-code: .* no pinned digest for the float "
                                          f"environment {re.escape(level)}"):
        equivalence.check_equivalence(load_report(grid))
    verdict = equivalence.check_equivalence(load_report(grid), str(tmp_path))
    assert verdict.startswith("new0000000000001: accepted by")
    report = load_report(grid)
    assert report.code == (CODE, "new0000000000001")
    assert report.equivalence[1] == ((level, "d" * 64, CODE),)
    assert "already accepted" in equivalence.check_equivalence(report)
    made["current"] = ("e" * 64, "new0000000000002")
    monkeypatch.setattr(equivalence, "source_hash", lambda: "new0000000000002")
    with pytest.raises(ConfigError, match="does not reproduce the pinned run"):
        equivalence.check_equivalence(load_report(grid))
    assert load_report(grid).code == (CODE, "new0000000000001")
    made["reference"] = ("d" * 64, "0" * 16)              # a reference the grid does not accept
    grid.write_text(GRID + PINNED.format(fern=FERN))
    with pytest.raises(ConfigError, match="holds code 0{16}, not code"):
        equivalence.check_equivalence(load_report(grid), str(tmp_path))
    assert tomllib.loads(grid.read_text())["report"]["equivalence"].get("pin") is None


@pytest.mark.slow
@pytest.mark.skipif(not (FERN / "sparse").is_dir(), reason="needs ../shared/data/fern")
def test_the_pinned_run_is_reproduced_bit_for_bit(tmp_path):
    """This checkout's code run twice gives the same digest, so pinned to it, it accepts
    itself (two 20-iteration runs of fern at 1/8 of images_8)."""
    grid = pinned_grid(tmp_path)
    argv, _ = load_report(grid).equivalence
    (tmp_path / "a").mkdir()
    digest, code = equivalence.run_code(equivalence.code_root(), list(argv), tmp_path / "a" / "r")
    assert code == equivalence.source_hash()
    grid.write_text(grid.read_text().replace(f'hash = "{CODE}"', 'hash = "other00000000000"'))
    equivalence.append_entry(grid, "report.equivalence.pin", {
        "float_environment": float_environment_key(), "digest": digest, "code": "other00000000000"})
    assert equivalence.check_equivalence(load_report(grid)).startswith(f"{code}: accepted")
    assert code in load_report(grid).code


def test_the_documented_example_is_a_valid_report(tmp_path):
    """docs/sweeps.md's complete [report] example loads and reports (no records yet)."""
    doc = (ROOT / "docs" / "sweeps.md").read_text(encoding="utf-8")
    start = doc.index("```toml\n# experiments/my_study.toml") + len("```toml\n")
    example = doc[start:].split("```", 1)[0]
    grid = tmp_path / "experiments" / "my_study.toml"
    grid.parent.mkdir()
    grid.write_text(example)
    (tmp_path / "records").mkdir()
    report = load_report(grid)
    assert report.marker == "my_study" and report.comparisons == (("fm[gamma=1.5]", "3dgs"),)
    md = report_markdown(report, tmp_path / "records")
    assert "### Beside the paper" in md and "No campaign records yet." in md
    assert "| fern | 3 | fm[gamma=1.5] | 0 |  | running or not yet run |" in md
