"""The tables of a grid's report, as Markdown, from its records (FM-13, FM-15, FM-16).

- ``means_table``: per (scene, views) and method, n, the seeds, each metric as mean +- sample
  std over the seeds (the value for one seed) and the record ids; a cell or seed without a
  record says ``MISSING``.  Layout "scene": scene, views and method label; layout "method": the
  method's name and views, with the quoted reference numbers beside (refgs.analysis.report_spec).
- ``diffs_table``: per (scene, views) and comparison, method - baseline paired by seed
  (``stats.paired_stats``): per metric the mean paired difference with its Student-t 95 % CI
  (bold where it excludes 0), the paired t-test p and the runs needed at 80 % power; one pair
  gives the mean only; then, optionally, the same pooled over the groups (every (scene, seed)
  pair one difference).
- ``paper_table``: per quoted (scene, views) and metric, each method's mean and each comparison
  as "ours / quoted" (differences of means).
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .stats import ALPHA, CONFIDENCE, MAX_RUNS_NEEDED, POWER, excludes_zero, paired_stats

#: What a cell without a record says (the records cannot tell a running run from a pending one).
MISSING = "running or not yet run"
NO_PAIRS = "no pairs yet"
POOLED = "pooled"
#: Line width of the generated prose (that of docs/results.md).
PROSE_WIDTH = 100
#: Counts written as words in the prose ("the four scenes").
NUMBER_WORDS = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine",
                "ten", "eleven", "twelve")


@dataclass(frozen=True)
class ReportRun:
    """One record counted by a report: its cell and its test-view means."""

    record: str
    scene: str
    views: int
    method: str
    seed: int
    metrics: dict


# --- cells ----------------------------------------------------------------------------------
def metric(r: ReportRun, key: str):
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


def prose(text: str) -> str:
    return textwrap.fill(text, PROSE_WIDTH, break_long_words=False, break_on_hyphens=False)


def row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def head(titles: list[str]) -> list[str]:
    return [row(titles), "|" + "---|" * len(titles)]


def of_cell(runs: list[ReportRun], scene: str, views: int, method: str) -> list[ReportRun]:
    return sorted((r for r in runs if (r.scene, r.views, r.method) == (scene, views, method)),
                  key=lambda r: r.seed)


def missing_note(rs: list[ReportRun], seeds: tuple) -> str:
    """The record ids of a cell, then the seeds it lacks."""
    missing = [s for s in seeds if s not in {r.seed for r in rs}]
    note = ", ".join(f"`{r.record}`" for r in rs)
    if missing and rs:
        note += f"; seed{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))}: {MISSING}"
    return note


# --- tables ---------------------------------------------------------------------------------
def means_table(report, part, runs: list[ReportRun], quoted) -> str:
    """The part's table of means (module docstring); ``quoted(scene, views, method)`` gives the
    quoted values of a row or None."""
    titles = [m.title for m in report.metrics]
    if part.layout == "scene":
        lines = head(["scene", "views", "method", "n", "seeds", *titles, "records"])
    else:
        lines = head(["method", "views", "n", "seeds", *titles,
                      "paper (" + " / ".join(titles) + ")", "records"])
    for scene, views in part.groups:
        for method in part.methods:
            rs = of_cell(runs, scene, views, method)
            name = part.names.get(method, report.display(method))
            cells = ([scene, str(views), method] if part.layout == "scene"
                     else [name, str(views)])
            cells += [str(len(rs)), ", ".join(str(r.seed) for r in rs)]
            if rs:
                cells += [mean_std([metric(r, m.key) for r in rs], m.decimals)
                          for m in report.metrics]
            else:
                cells += [MISSING] + [""] * (len(report.metrics) - 1)
            if part.layout == "method":
                q = quoted(scene, views, method)
                cells.append("-" if q is None else " / ".join(
                    f"{v:.{m.decimals}f}" for v, m in zip(q, report.metrics)))
            cells.append(missing_note(rs, report.seeds))
            lines.append(row(cells))
    return "\n".join(lines)


def pairs_of(runs: list[ReportRun], method: str, base: str, groups, seeds) -> list[tuple]:
    """[(scene, seed, method run, baseline run)] of the seeds both have, in the groups given."""
    by = {(r.scene, r.views, r.method, r.seed): r for r in runs}
    return [(scene, seed, by[(scene, views, method, seed)], by[(scene, views, base, seed)])
            for scene, views in groups for seed in seeds
            if (scene, views, method, seed) in by and (scene, views, base, seed) in by]


def diff_row(metrics, label: list[str], pairs: list[tuple]) -> str:
    """A row of the differences table: ``label`` cells, the pairs, then per metric its cells."""
    if not pairs:
        return row([*label, "0", NO_PAIRS] + [""] * (3 * len(metrics) - 1))
    cells = list(label)
    scenes = list(dict.fromkeys(p[0] for p in pairs))
    n = str(len(pairs))
    if label[0] == POOLED:
        n += " (" + ", ".join(f"{s} {sum(p[0] == s for p in pairs)}" for s in scenes) + ")"
    cells.append(n)
    for m in metrics:
        diffs = [(metric(a, m.key), metric(b, m.key)) for _, _, a, b in pairs]
        ok = all(x is not None and y is not None for x, y in diffs)
        cells += diff_cells(paired_stats([x - y for x, y in diffs]) if ok else None, m.decimals)
    return row(cells)


def diffs_table(report, part, runs: list[ReportRun]) -> str:
    titles = ["scene", "views", "difference", "pairs"]
    for m in report.metrics:
        titles += [f"Δ {m.title} [{percent(CONFIDENCE)} CI]", f"p ({m.title})",
                   f"runs needed ({m.title})"]
    lines = head(titles)
    names = {c: f"{report.display(c[0])} − {report.display(c[1])}" for c in part.comparisons}
    for scene, views in part.groups:
        for c in part.comparisons:
            lines.append(diff_row(report.metrics, [scene, str(views), names[c]],
                                  pairs_of(runs, *c, [(scene, views)], report.seeds)))
    if part.pooled:
        all_views = ", ".join(str(v) for v in dict.fromkeys(v for _, v in part.groups))
        for c in part.comparisons:
            lines.append(diff_row(report.metrics, [POOLED, all_views, names[c]],
                                  pairs_of(runs, *c, part.groups, report.seeds)))
    return "\n".join(lines)


def diffs_prose(report, part) -> str:
    """What the differences table holds (before it, in a part that explains itself)."""
    firsts = {a for a, _ in part.comparisons}
    who = report.display(firsts.pop()) if len(firsts) == 1 else "the method"
    lpips = [m for m in report.metrics if m.key.startswith("lpips")]
    units = (f"seed by seed, in the metric's own units: lower LPIPS is better, so a negative "
             f"Δ {lpips[0].title} favours {who}" if lpips else "seed by seed, in the metric's "
             "own units")
    return prose(f"Paired differences, method − baseline, over the seeds both have ({units}); "
                 f"{percent(CONFIDENCE)} Student-t CI, **bold** where it excludes 0; p of the "
                 "paired t-test; runs needed: seeds at which the observed mean difference is "
                 f"detected with {percent(POWER)} power at α = {ALPHA} given the observed spread "
                 "(FM-16).")


def pooled_prose(part) -> str:
    n = len(part.groups)
    count = NUMBER_WORDS[n] if n < len(NUMBER_WORDS) else str(n)
    return prose(f"The pooled rows treat every (scene, seed) pair of the {count} scenes as one "
                 "paired difference: their mean, the Student-t CI and the t-test over all those "
                 "pairs (n = the number of pairs, per scene in brackets); scenes with more pairs "
                 "weigh more, and the differences between scenes count as spread.")


def number(v, decimals: int) -> str:
    return "-" if v is None else f"{v:.{decimals}f}"


def difference(a, b, decimals: int) -> str:
    return "-" if a is None or b is None else f"{a - b:+.{decimals}f}"


def paper_table(report, runs: list[ReportRun]) -> str:
    """The report's quotes beside our means (module docstring)."""
    methods, comparisons = report.methods, report.comparisons
    lines = head(["scene", "paper's mean over", "metric", "seeds (ours)",
                  *(report.display(m) for m in methods),
                  *(f"{report.display(a)} − {report.display(b)}" for a, b in comparisons)])
    for q in report.quotes:
        for i, m in enumerate(report.metrics):
            ours = {}
            for method in methods:
                vals = [metric(r, m.key) for r in of_cell(runs, q.scene, q.views, method)]
                vals = [v for v in vals if v is not None]
                ours[method] = (float(np.mean(vals)), len(vals)) if vals else (None, 0)
            cells = [f"{q.scene} {q.views}-view", q.over, m.title,
                     "/".join(str(ours[x][1]) for x in methods)]
            theirs = {x: q.values[x][i] if x in q.values else None for x in methods}
            for x in methods:
                cells.append(f"{number(ours[x][0], m.decimals)} / "
                             f"{number(theirs[x], m.decimals)}")
            for a, b in comparisons:
                cells.append(f"{difference(ours[a][0], ours[b][0], m.decimals)} / "
                             f"{difference(theirs[a], theirs[b], m.decimals)}")
            lines.append(row(cells))
    return "\n".join(lines)


__all__ = ["ReportRun", "MISSING", "NO_PAIRS", "POOLED", "metric", "mean_std", "percent",
           "p_text", "diff_cells", "prose", "row", "head", "of_cell", "means_table",
           "diffs_table", "diffs_prose", "pooled_prose", "paper_table", "pairs_of", "diff_row"]
