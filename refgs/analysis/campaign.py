"""The main campaign's table in docs/results.md, built from its records (FM-13, FM-15, FM-16).

The campaign is the grid ``experiments/paper_main.toml`` (``CAMPAIGN_*``): fern and desk at 3
views, bonsai and cup at 12; 3DGS, DropGaussian and FM; seeds 0, 1, 2; 10,000 iterations with
the fast backend.  A record belongs to it when its ``config.json`` command is the grid's worker,
``refgs run-one <...>/experiments/paper_main.toml --out ... --name ...`` (what ``refgs sweep`` and
``refgs run-one`` both write, refgs.sweep.execute); its settings must then be a cell of the grid
(ConfigError naming the record otherwise).  Every other record is left to the summary families.

The Markdown has two tables and a sentence:

- per scene and method: n, the seeds, PSNR / SSIM / LPIPS-VGG as mean +- sample std over seeds
  (the value for one seed) and the record ids; missing seeds and cells say ``MISSING``;
- per scene, FM - 3DGS and FM - DropGaussian paired by seed (``stats.paired_stats``): per metric
  the mean paired difference with its Student-t 95 % CI, the paired t-test p and the runs needed
  at 80 % power; one pair gives the mean only; then the same pooled over the four scenes, every
  (scene, seed) pair one difference.
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path, PurePath

import numpy as np

from ..errors import ConfigError
from ..runs import CONFIG_FILE, METRICS_FILE
from .stats import ALPHA, CONFIDENCE, MAX_RUNS_NEEDED, POWER, excludes_zero, paired_stats
from .tables import method_label, read_run_json

#: The grid of the campaign, as the tail of the path in a record's command.
CAMPAIGN_GRID = "experiments/paper_main.toml"
#: Source hashes (refgs.train.checkpoint.source_hash, in each record's provenance) of the
#: campaign's training code: commit 1054ec1 and the commits since 1b670c0 that changed no file of
#: refgs/ (docs/results.md, "One version of the code").
CAMPAIGN_SOURCE_HASHES = ("f46384a1bad7227b",)
#: The worker command of a grid run: ``refgs run-one GRID --out DIR --name NAME``.
RUN_ONE = "run-one"
#: (scene folder name, views) of the grid's two groups, in the table's order.
CAMPAIGN_SCENES = (("fern", 3), ("desk", 3), ("bonsai", 12), ("cup", 12))
CAMPAIGN_METHODS = ("3dgs", "dropgaussian", "fm")
CAMPAIGN_SEEDS = (0, 1, 2)
#: Settings every run of the grid has (the grid's top-level keys).
CAMPAIGN_SETTINGS = {"iters": 10_000, "backend": "fast", "images": "images_8"}
#: (method, baseline): the paired differences reported, method minus baseline.
COMPARISONS = (("fm", "3dgs"), ("fm", "dropgaussian"))
#: (metrics.json key, column title, decimals shown): the paper's three metrics.
METRICS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("lpips_vgg", "LPIPS-VGG", 3))
#: What a cell without a record says (the records cannot tell a running run from a pending one).
MISSING = "running or not yet run"
NO_PAIRS = "no pairs yet"
TITLE = "Main campaign: 3DGS, DropGaussian and FM over seeds"
POOLED = "pooled"
#: Display names of the method labels.
DISPLAY = {"3dgs": "3DGS", "dropgaussian": "DropGaussian", "fm": "FM"}
#: Line width of the generated prose (that of docs/results.md).
PROSE_WIDTH = 100


@dataclass(frozen=True)
class CampaignRun:
    """One record of the campaign: its cell and its test-view means."""

    record: str
    scene: str
    views: int
    method: str
    seed: int
    metrics: dict


def made_by_campaign(config: dict, grid_file: str = CAMPAIGN_GRID) -> bool:
    """Whether a run's config.json command is ``refgs run-one .../<grid_file> ...`` (the
    campaign's grid by default)."""
    cmd = config.get("command")
    if not isinstance(cmd, list) or len(cmd) < 3 or cmd[1] != RUN_ONE:
        return False
    grid, tail = PurePath(str(cmd[2])).parts, PurePath(grid_file).parts
    return grid[-len(tail):] == tail


def record_cell(folder: Path, config: dict, grid_file: str) -> tuple[tuple, dict, str]:
    """(cell (scene, views, method label, seed), the grid-wide settings that differ from
    CAMPAIGN_SETTINGS, the error prefix naming the record) of a record made by ``grid_file``;
    ConfigError naming the record when its settings lack a part of the cell."""
    s = config.get("settings")
    where = f"{folder / CONFIG_FILE}: made by {grid_file} but"
    if not isinstance(s, dict):
        raise ConfigError(f"{where} has no 'settings' object")
    try:
        cell = (Path(s["scene"]).name, int(s["views"]), method_label(s), int(s["seed"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where} its settings lack scene, views or seed ({exc})") from None
    other = {k: s.get(k) for k, v in CAMPAIGN_SETTINGS.items() if s.get(k) != v}
    return cell, other, where


def campaign_run(folder: Path, config: dict) -> CampaignRun:
    """The CampaignRun of a campaign record; ConfigError naming the record when its settings
    are not a cell of the grid."""
    cell, other, where = record_cell(folder, config, CAMPAIGN_GRID)
    if (cell[:2] not in CAMPAIGN_SCENES or cell[2] not in CAMPAIGN_METHODS
            or cell[3] not in CAMPAIGN_SEEDS or other):
        raise ConfigError(f"{where} scene {cell[0]}, views {cell[1]}, method {cell[2]}, seed "
                          f"{cell[3]}{', ' + str(other) if other else ''} is not a cell of the "
                          "campaign (CAMPAIGN_* in refgs/analysis/campaign.py)")
    return CampaignRun(folder.name, *cell, read_run_json(folder / METRICS_FILE))


def load_grid_records(records_dir: str | Path, grid_file: str = CAMPAIGN_GRID,
                      make_run=campaign_run) -> list[CampaignRun]:
    """The records among the folders of ``records_dir`` made by ``grid_file`` (others are
    skipped), each read by ``make_run(folder, config)``; ConfigError naming both records when two
    share a cell."""
    if not Path(records_dir).is_dir():
        raise ConfigError(f"{records_dir}: not a folder (expected results/records)")
    out, seen = [], {}
    for folder in sorted(p for p in Path(records_dir).iterdir() if p.is_dir()):
        if not (folder / CONFIG_FILE).is_file():
            continue
        config = read_run_json(folder / CONFIG_FILE)
        if not made_by_campaign(config, grid_file):
            continue
        r = make_run(folder, config)
        key = (r.scene, r.views, r.method, r.seed)
        if key in seen:
            raise ConfigError(f"{folder}: same scene, views, method and seed as {seen[key]}")
        seen[key] = folder.name
        out.append(r)
    return out


def load_campaign(records_dir: str | Path) -> list[CampaignRun]:
    """The campaign's records among the folders of ``records_dir`` (load_grid_records)."""
    return load_grid_records(records_dir)


# --- formatting -----------------------------------------------------------------------------
def metric(r: CampaignRun, key: str):
    """A metric of a record as a float, None where it has none; ConfigError if not a number."""
    v = r.metrics.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ConfigError(f"{r.record}/metrics.json: {key} = {v!r}, expected a finite number")
    return float(v)


def mean_std(values: list, decimals: int) -> str:
    """``m ± s`` (sample std) for several values, the value for one, ``n/a`` if any is None."""
    if any(v is None for v in values):
        return "n/a"
    a = np.asarray(values, np.float64)
    return (f"{a[0]:.{decimals}f}" if a.size == 1
            else f"{a.mean():.{decimals}f} ± {a.std(ddof=1):.{decimals}f}")


def percent(x: float) -> str:
    return f"{100 * x:.0f} %"


def p_text(p) -> str:
    return "-" if p is None else (f"{p:.3f}" if p >= 1e-3 else f"{p:.1e}")


def diff_cells(st: dict | None, decimals: int) -> list[str]:
    """[Δ with its CI (bold where the CI excludes 0), p, runs needed] of ``paired_stats``."""
    if st is None:
        return ["n/a", "", ""]
    d = f"{st['mean_diff']:+.{decimals}f}"
    if st["ci95"] is None:
        return [f"{d} ({st['note']})", "-", "-"]
    lo, hi = st["ci95"]
    d = f"**{d}**" if excludes_zero(st["ci95"]) else d
    need = st["runs_needed"]
    need = (str(need) if need is not None
            else f"> {MAX_RUNS_NEEDED}" if st["mean_diff"] != 0.0 else "-")
    return [f"{d} [{lo:+.{decimals}f}, {hi:+.{decimals}f}]", p_text(st["p_value"]), need]


def pairs_of(runs: list[CampaignRun], method: str, base: str, cells) -> list[tuple]:
    """[(scene, seed, method run, baseline run)] of the seeds both have, in the cells given."""
    by = {(r.scene, r.views, r.method, r.seed): r for r in runs}
    return [(scene, seed, by[(scene, views, method, seed)], by[(scene, views, base, seed)])
            for scene, views in cells for seed in CAMPAIGN_SEEDS
            if (scene, views, method, seed) in by and (scene, views, base, seed) in by]


def diff_row(label: list[str], pairs: list[tuple]) -> str:
    """A row of the differences table: ``label`` cells, the pairs, then per metric its cells."""
    if not pairs:
        cells = [*label, "0", NO_PAIRS] + [""] * (3 * len(METRICS) - 1)
        return "| " + " | ".join(cells) + " |"
    cells = list(label)
    scenes = list(dict.fromkeys(p[0] for p in pairs))
    n = str(len(pairs))
    if label[0] == POOLED:
        n += " (" + ", ".join(f"{s} {sum(p[0] == s for p in pairs)}" for s in scenes) + ")"
    cells.append(n)
    for key, _, dec in METRICS:
        diffs = [(metric(a, key), metric(b, key)) for _, _, a, b in pairs]
        ok = all(x is not None and y is not None for x, y in diffs)
        cells += diff_cells(paired_stats([x - y for x, y in diffs]) if ok else None, dec)
    return "| " + " | ".join(cells) + " |"


def means_table(runs: list[CampaignRun]) -> str:
    head = ["scene", "views", "method", "n", "seeds", *(t for _, t, _ in METRICS), "records"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, views in CAMPAIGN_SCENES:
        for method in CAMPAIGN_METHODS:
            rs = sorted((r for r in runs if (r.scene, r.views, r.method) == (scene, views, method)),
                        key=lambda r: r.seed)
            cells = [scene, str(views), method, str(len(rs)), ", ".join(str(r.seed) for r in rs)]
            if not rs:
                cells += [MISSING] + [""] * len(METRICS)
            else:
                cells += [mean_std([metric(r, k) for r in rs], d) for k, _, d in METRICS]
                missing = [s for s in CAMPAIGN_SEEDS if s not in {r.seed for r in rs}]
                note = ", ".join(f"`{r.record}`" for r in rs)
                if missing:
                    note += f"; seed{'s' if len(missing) > 1 else ''} " \
                            f"{', '.join(map(str, missing))}: {MISSING}"
                cells.append(note)
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def diffs_head() -> list[str]:
    """The header lines of a table of ``diff_row`` rows."""
    head = ["scene", "views", "difference", "pairs"]
    for _, t, _ in METRICS:
        head += [f"Δ {t} [{percent(CONFIDENCE)} CI]", f"p ({t})", f"runs needed ({t})"]
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]


def diffs_table(runs: list[CampaignRun]) -> str:
    lines = diffs_head()
    names = {c: f"{DISPLAY[c[0]]} − {DISPLAY[c[1]]}" for c in COMPARISONS}
    for scene, views in CAMPAIGN_SCENES:
        for c in COMPARISONS:
            pairs = pairs_of(runs, *c, [(scene, views)])
            lines.append(diff_row([scene, str(views), names[c]], pairs))
    all_views = ", ".join(str(v) for v in dict.fromkeys(v for _, v in CAMPAIGN_SCENES))
    for c in COMPARISONS:
        lines.append(diff_row([POOLED, all_views, names[c]], pairs_of(runs, *c, CAMPAIGN_SCENES)))
    return "\n".join(lines)


def prose(text: str) -> str:
    return textwrap.fill(text, PROSE_WIDTH, break_long_words=False, break_on_hyphens=False)


def campaign_markdown(records_dir: str | Path) -> str:
    """The Markdown of the campaign block (module docstring) from the records of
    ``records_dir``; cells without records say so."""
    runs = load_campaign(records_dir)
    scenes = ", ".join(f"{s} ({v} views)" for s, v in CAMPAIGN_SCENES)
    s = CAMPAIGN_SETTINGS
    return "\n".join([
        f"## {TITLE}", "",
        prose(f"The grid `{CAMPAIGN_GRID}`: {scenes}; seeds {', '.join(map(str, CAMPAIGN_SEEDS))}; "
        f"{s['iters']:,} iterations, `{s['images']}`, the {s['backend']} backend. Only records "
        f"made by this grid count (their `config.json` command is `refgs {RUN_ONE} "
        f"{CAMPAIGN_GRID} ...`). Mean ± sample standard deviation over the seeds, n the number "
        "of seeds."), "",
        means_table(runs), "",
        prose("Paired differences, method − baseline, over the seeds both have (seed by seed, "
              "in the metric's own units: lower LPIPS is better, so a negative Δ LPIPS-VGG "
              f"favours FM); {percent(CONFIDENCE)} Student-t CI, **bold** where it excludes 0; p of the "
              "paired t-test; runs needed: seeds at which the observed mean difference is "
              f"detected with {percent(POWER)} power at α = {ALPHA} given the observed spread "
              "(FM-16)."), "",
        diffs_table(runs), "",
        prose("The pooled rows treat every (scene, seed) pair of the four scenes as one paired "
        "difference: their mean, the Student-t CI and the t-test over all those pairs (n = the "
        "number of pairs, per scene in brackets); scenes with more pairs weigh more, and the "
        "differences between scenes count as spread."), ""])


__all__ = ["CAMPAIGN_GRID", "CAMPAIGN_SOURCE_HASHES", "CAMPAIGN_SCENES", "CAMPAIGN_METHODS", "CAMPAIGN_SEEDS",
           "CAMPAIGN_SETTINGS", "COMPARISONS", "MISSING", "NO_PAIRS", "CampaignRun",
           "made_by_campaign", "record_cell", "campaign_run", "load_grid_records", "load_campaign", "campaign_markdown", "diffs_head",
           "diff_row", "pairs_of", "mean_std", "metric", "prose"]
