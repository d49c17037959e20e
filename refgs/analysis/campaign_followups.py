"""The main campaign's follow-ups on fern: two ablations of FM and 6 / 9 training views.

The grid ``experiments/paper_followups.toml`` (``FOLLOWUPS_GRID``): on fern, seeds 0, 1, 2 and the
main campaign's settings (``campaign.CAMPAIGN_SETTINGS``), FM without reinitialisation and FM
without scheduling at 3 views, then 3DGS, DropGaussian and FM at 6 and 9 views.  A record belongs
to it when its ``config.json`` command is ``refgs run-one <...>/experiments/paper_followups.toml
...``; it must then be one of the grid's cells (``FOLLOWUP_CELLS``) and be made by the campaign's
training code (``campaign.CAMPAIGN_SOURCE_HASHES``), because its comparisons take the main
campaign's fern 3-view records as their 3-view rows and FM baseline (ConfigError naming the record
otherwise).

The Markdown has, for each part, a table of means and a table of paired differences:

- ablations: FM (the main campaign's fern 3-view FM records) and each ablation, mean +- sample std
  over seeds with the paper's value of the row beside (its ablation table, LLFF 3-view means);
  then ablation - FM paired by seed (``campaign.diff_row``: CI, p, runs needed);
- views: 3 (the main campaign's records), 6 and 9 views, each method's mean with the paper's LLFF
  mean beside; then FM - 3DGS and FM - DropGaussian paired by seed at each view count.
"""
from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError
from ..runs import METRICS_FILE
from .campaign import (CAMPAIGN_SEEDS, CAMPAIGN_SETTINGS, CAMPAIGN_SOURCE_HASHES, COMPARISONS,
                       DISPLAY, METRICS, MISSING, CampaignRun, diff_row, diffs_head,
                       load_campaign, load_grid_records, mean_std, metric, pairs_of, prose,
                       record_cell)
from .campaign_paper import PAPER
from .tables import read_run_json

#: The follow-ups' grid, as the tail of the path in a record's command.
FOLLOWUPS_GRID = "experiments/paper_followups.toml"
SCENE = "fern"
#: The ablations (method labels, refgs.analysis.tables.method_label) and their names.
ABLATIONS = {"fm[reinit=False]": "FM w/o reinitialisation",
             "fm[schedule=False]": "FM w/o scheduling"}
VIEWS = (3, 6, 9)
#: (views, method label) of every cell of the grid; the 3-view methods come from the main
#: campaign.
FOLLOWUP_CELLS = ({(3, a) for a in ABLATIONS}
                  | {(v, m) for v in VIEWS[1:] for m in ("3dgs", "dropgaussian", "fm")})
#: The paper's ablation table ("Ablation studies on the LLFF dataset under the 3-view setting",
#: rows Full Method, w/o Scheduling, w/o Reinitialization): (PSNR, SSIM, LPIPS).
PAPER_ABLATIONS = {"fm": (20.88, 0.731, 0.184), "fm[schedule=False]": (20.69, 0.721, 0.191),
                   "fm[reinit=False]": (20.58, 0.713, 0.197)}
#: The paper's LLFF table ("Quantitative comparison on the LLFF dataset under 3-view, 6-view,
#: and 9-view settings"), rows 3DGS, DropGaussian, Ours: (PSNR, SSIM, LPIPS); 3 views from
#: campaign_paper.PAPER.
PAPER_VIEWS = {
    3: PAPER[(SCENE, 3)][1],
    6: {"3dgs": (23.80, 0.814, 0.125), "dropgaussian": (24.74, 0.837, 0.117),
        "fm": (24.76, 0.840, 0.114)},
    9: {"3dgs": (25.44, 0.860, 0.096), "dropgaussian": (26.21, 0.874, 0.088),
        "fm": (26.23, 0.875, 0.088)},
}
TITLE = "Follow-ups on fern: two ablations of FM, 6 and 9 views"


def followup_run(folder: Path, config: dict) -> CampaignRun:
    """The CampaignRun of a follow-up record; ConfigError naming the record when its settings are
    not a cell of the grid or another training code made it."""
    cell, other, where = record_cell(folder, config, FOLLOWUPS_GRID)
    if cell[0] != SCENE or cell[1:3] not in FOLLOWUP_CELLS or cell[3] not in CAMPAIGN_SEEDS or other:
        raise ConfigError(f"{where} scene {cell[0]}, views {cell[1]}, method {cell[2]}, seed "
                          f"{cell[3]}{', ' + str(other) if other else ''} is not one of its cells "
                          "(FOLLOWUP_CELLS in refgs/analysis/campaign_followups.py)")
    code = (config.get("provenance") or {}).get("source_hash")
    if code not in CAMPAIGN_SOURCE_HASHES:
        raise ConfigError(f"{where} its source hash {code} is not the main campaign's "
                          f"({', '.join(CAMPAIGN_SOURCE_HASHES)}): rerun it from that checkout")
    return CampaignRun(folder.name, *cell, read_run_json(folder / METRICS_FILE))


def load_followups(records_dir: str | Path) -> list[CampaignRun]:
    """The follow-ups' records among the folders of ``records_dir`` (others are skipped);
    ConfigError naming both records when two share a cell."""
    return load_grid_records(records_dir, FOLLOWUPS_GRID, followup_run)


def paper_cell(values: tuple) -> str:
    return " / ".join(f"{v:.{d}f}" for v, (_, _, d) in zip(values, METRICS))


def means_row(name: str, views: int, rs: list[CampaignRun], paper: tuple) -> str:
    """A row of a means table: the row's name, views, n, seeds, per metric mean +- std, the
    paper's values and the record ids (or what is missing)."""
    rs = sorted(rs, key=lambda r: r.seed)
    cells = [name, str(views), str(len(rs)), ", ".join(str(r.seed) for r in rs)]
    if rs:
        cells += [mean_std([metric(r, k) for r in rs], d) for k, _, d in METRICS]
    else:
        cells += [MISSING] + [""] * (len(METRICS) - 1)
    cells.append(paper_cell(paper))
    missing = [s for s in CAMPAIGN_SEEDS if s not in {r.seed for r in rs}]
    note = ", ".join(f"`{r.record}`" for r in rs)
    if missing and rs:
        note += f"; seed{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))}: {MISSING}"
    cells.append(note)
    return "| " + " | ".join(cells) + " |"


def means_head(first: str) -> list[str]:
    head = [first, "views", "n", "seeds", *(t for _, t, _ in METRICS),
            "paper (" + " / ".join(t for _, t, _ in METRICS) + ")", "records"]
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]


def followups_markdown(records_dir: str | Path) -> str:
    """The Markdown of the follow-ups' block (module docstring) from the records of
    ``records_dir``; cells without records say so."""
    runs = [r for r in load_campaign(records_dir) if (r.scene, r.views) == (SCENE, 3)]
    runs += load_followups(records_dir)

    def of(views: int, method: str) -> list[CampaignRun]:
        return [r for r in runs if (r.views, r.method) == (views, method)]

    ablation_means = means_head("method")
    ablation_means.append(means_row("FM (main campaign)", 3, of(3, "fm"), PAPER_ABLATIONS["fm"]))
    for label, name in ABLATIONS.items():
        ablation_means.append(means_row(name, 3, of(3, label), PAPER_ABLATIONS[label]))
    ablation_diffs = diffs_head()
    for label, name in ABLATIONS.items():
        ablation_diffs.append(diff_row([SCENE, "3", f"{name} − FM"],
                                       pairs_of(runs, label, "fm", [(SCENE, 3)])))
    view_means = means_head("method")
    for views in VIEWS:
        for m in ("3dgs", "dropgaussian", "fm"):
            view_means.append(means_row(DISPLAY[m], views, of(views, m), PAPER_VIEWS[views][m]))
    view_diffs = diffs_head()
    for views in VIEWS:
        for a, b in COMPARISONS:
            view_diffs.append(diff_row([SCENE, str(views), f"{DISPLAY[a]} − {DISPLAY[b]}"],
                                       pairs_of(runs, a, b, [(SCENE, views)])))
    s = CAMPAIGN_SETTINGS
    return "\n".join([
        f"## {TITLE}", "",
        prose(f"The grid `{FOLLOWUPS_GRID}`, run with the main campaign's training code and "
              f"settings ({s['iters']:,} iterations, `{s['images']}`, the {s['backend']} "
              f"backend; seeds {', '.join(map(str, CAMPAIGN_SEEDS))}): the two ablations with "
              "the largest effect in the paper's ablation table at 3 views, and the three "
              "methods at 6 and 9 views. The 3-view FM, 3DGS and DropGaussian rows are the main "
              "campaign's fern records. The paper's values are LLFF means over its 8 scenes; "
              "its ablations lose " + ", ".join(
                  f"{PAPER_ABLATIONS[a][0] - PAPER_ABLATIONS['fm'][0]:+.2f} dB PSNR ({n[3:]})"
                  for a, n in ABLATIONS.items()) + " against its full method."),
        "", "*Ablations, fern 3-view* (the ablation minus FM, paired by seed):", "",
        "\n".join(ablation_means), "", "\n".join(ablation_diffs), "",
        "*Views, fern* (FM minus each baseline, paired by seed):", "",
        "\n".join(view_means), "", "\n".join(view_diffs), ""])


__all__ = ["FOLLOWUPS_GRID", "ABLATIONS", "FOLLOWUP_CELLS", "PAPER_ABLATIONS", "PAPER_VIEWS",
           "followup_run", "load_followups", "followups_markdown"]
