"""``refgs report``: the report of any grid with a ``[report]`` table, built from its records
(FM-13, FM-15, FM-16; the table's format: refgs.analysis.report_spec, docs/sweeps.md).

    refgs report GRID.toml ... [--records results/records] [--update docs/results.md]
    refgs report GRID.toml --check-equivalence [--reference-code DIR]     (refgs.analysis.equivalence)

A record counts for a grid when its ``config.json`` command is ``refgs run-one .../GRID ...``, its
cell (scene folder, views, method label, seed) is one of the grid's, its settings are those the
grid file names for that cell, and its training code (``provenance.source_hash``) is one the
report accepts (``[[report.code]]``; any code when it lists none).  Anything else made by the grid
is refused with a ConfigError naming the record; two records of one cell are refused too.

The block of a grid: its title and intro, then per part a table of means and one of paired
differences (refgs.analysis.report_tables), then where declared the quoted numbers beside ours,
the flatness over training seeds (refgs.analysis.flatness_drops) and the cost
(refgs.analysis.cost).  In a document the block sits between ``<!-- MARKER:begin -->`` and
``<!-- MARKER:end -->`` (``marker``, default the grid's file stem); ``--update FILE`` rewrites it
in place (atomically), and the summary block (``SUMMARY_MARKERS``: refgs.analysis.summary, the
records no reported grid beside the given ones claims) where FILE has one.
tests/test_results_doc.py checks that docs/results.md's blocks are exactly this output.
"""
from __future__ import annotations

import sys
from pathlib import Path

from ..errors import ConfigError
from ..io.atomic import atomic_write_text
from ..runs import CONFIG_FILE, METRICS_FILE
from .cost import cost_markdown
from .flatness_drops import flatness_markdown
from .report_spec import Report, has_report, load_report, made_by, quoted
from .report_tables import (ReportRun, diffs_prose, diffs_table, means_table, paper_table,
                            pooled_prose, prose)
from .summary import default_unrecorded, summary_markdown
from .tables import method_label, read_run_json

#: The summary block's markers (refgs.analysis.summary).
SUMMARY_MARKERS = ("<!-- summary:begin -->", "<!-- summary:end -->")
DEFAULT_RECORDS = "results/records"
PAPER_HEADING = "### Beside the paper"


def markers(report: Report) -> tuple[str, str]:
    return f"<!-- {report.marker}:begin -->", f"<!-- {report.marker}:end -->"


# --- records --------------------------------------------------------------------------------
def report_run(folder: Path, config: dict, report: Report) -> ReportRun:
    """The ReportRun of a record made by the report's grid; ConfigError naming the record when
    it is not a cell of the grid, has other settings, or other training code made it."""
    s = config.get("settings")
    where = f"{folder / CONFIG_FILE}: made by {report.name} but"
    if not isinstance(s, dict):
        raise ConfigError(f"{where} has no 'settings' object")
    try:
        cell = (Path(s["scene"]).name, int(s["views"]), method_label(s), int(s["seed"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where} its settings lack scene, views or seed ({exc})") from None
    named = report.cells.get(cell)
    other = {} if named is None else {k: s.get(k) for k, v in named.items() if s.get(k) != v}
    if named is None or other:
        raise ConfigError(f"{where} scene {cell[0]}, views {cell[1]}, method {cell[2]}, seed "
                          f"{cell[3]}{', ' + str(other) if other else ''} is not a cell of the "
                          f"grid (refgs sweep {report.name} --out DIR --list)")
    code = (config.get("provenance") or {}).get("source_hash")
    if report.code and code not in report.code:
        raise ConfigError(f"{where} its source hash {code} is not one the grid accepts "
                          f"({', '.join(report.code)}): check it with refgs report {report.name} "
                          "--check-equivalence, or rerun it with accepted code")
    return ReportRun(folder.name, *cell, read_run_json(folder / METRICS_FILE))


def load_runs(records_dir: str | Path, report: Report) -> list[ReportRun]:
    """The records among the folders of ``records_dir`` that the report's grid made (others
    are skipped); ConfigError naming both records when two share a cell."""
    if not Path(records_dir).is_dir():
        raise ConfigError(f"{records_dir}: not a folder (expected results/records)")
    out, seen = [], {}
    for folder in sorted(p for p in Path(records_dir).iterdir() if p.is_dir()):
        if not (folder / CONFIG_FILE).is_file():
            continue
        config = read_run_json(folder / CONFIG_FILE)
        if not made_by(config, report):
            continue
        r = report_run(folder, config, report)
        key = (r.scene, r.views, r.method, r.seed)
        if key in seen:
            raise ConfigError(f"{folder}: same scene, views, method and seed as {seen[key]}")
        seen[key] = folder.name
        out.append(r)
    return out


def all_runs(records_dir: str | Path, report: Report) -> list[ReportRun]:
    """The included grids' records, then the report's own (ConfigError when two grids record
    the same cell)."""
    runs = [r for inc in report.includes for r in all_runs(records_dir, inc)]
    runs += load_runs(records_dir, report)
    seen = {}
    for r in runs:
        key = (r.scene, r.views, r.method, r.seed)
        if key in seen:
            raise ConfigError(f"{records_dir}/{r.record}: same cell as {seen[key]} of another "
                              f"grid included by {report.name}")
        seen[key] = r.record
    return runs


# --- the block ------------------------------------------------------------------------------
def settings_phrase(settings: dict) -> str:
    """``10,000 iterations, `images_8`, the fast backend`` from the settings every run shares."""
    words = []
    if "iters" in settings:
        words.append(f"{settings['iters']:,} iterations")
    if settings.get("images"):
        words.append(f"`{settings['images']}`")
    if "backend" in settings:
        words.append(f"the {settings['backend']} backend")
    return ", ".join(words)


def intro_text(report: Report) -> str:
    """The report's intro with its placeholders filled (report_spec.DEFAULT_INTRO)."""
    fill = {"grid": report.name, "seeds": ", ".join(map(str, report.seeds)),
            "scenes": ", ".join(f"{s} ({v} views)" for s, v in report.groups),
            "settings": settings_phrase(report.settings)}
    try:
        return report.intro.format_map(fill)
    except (KeyError, ValueError, IndexError) as exc:
        raise ConfigError(f"{report.grid}: report.intro: unknown placeholder {exc} (expected "
                          f"{', '.join('{' + k + '}' for k in fill)})") from None


def report_markdown(report: Report, records_dir: str | Path) -> str:
    """The Markdown block of the report (module docstring) from the records of
    ``records_dir``; cells without records say so."""
    own = load_runs(records_dir, report)
    runs = all_runs(records_dir, report)
    blocks = [f"## {report.title}", prose(intro_text(report))]
    for part in report.parts:
        if part.caption:
            blocks.append(prose(part.caption))
        blocks.append(means_table(report, part, runs,
                                  lambda s, v, m: quoted(report, s, v, m)))
        if part.explain:
            blocks.append(diffs_prose(report, part))
        blocks.append(diffs_table(report, part, runs))
        if part.explain and part.pooled:
            blocks.append(pooled_prose(part))
    if report.paper_note is not None:
        blocks += [PAPER_HEADING] + ([prose(report.paper_note)] if report.paper_note else [])
        blocks.append(paper_table(report, own))
    if report.flatness_groups is not None:
        blocks.append(flatness_markdown(records_dir, report, own).rstrip())
    if report.cost_note is not None:
        blocks.append(cost_markdown(records_dir, own, report.groups, report.methods,
                                    report.cost_note).rstrip())
    return "\n\n".join(blocks) + "\n"


# --- the document ---------------------------------------------------------------------------
def split_document(text: str, name: str, begin: str, end: str) -> tuple[str, str, str]:
    """(before, block, after) around the one ``begin`` ... ``end`` pair; ConfigError naming
    ``name`` if the markers are missing, repeated or out of order."""
    if text.count(begin) != 1 or text.count(end) != 1:
        raise ConfigError(f"{name}: expected one {begin} and one {end} line")
    before, rest = text.split(begin)
    if end not in rest:
        raise ConfigError(f"{name}: {end} comes before {begin}")
    block, after = rest.split(end)
    return before + begin, block, end + after


def with_block(text: str, markdown: str, name: str, begin: str, end: str) -> str:
    """``text`` with its ``begin`` ... ``end`` block replaced by ``markdown`` (blank line on each
    side)."""
    before, _, after = split_document(text, name, begin, end)
    return f"{before}\n\n{markdown.strip()}\n\n{after}"


def reports_beside(grids) -> list[Report]:
    """Every grid with a [report] table in the folders of ``grids`` (the summary leaves their
    records to them)."""
    folders = dict.fromkeys(Path(g).absolute().parent for g in grids)
    return [load_report(p) for f in folders for p in sorted(f.glob("*.toml")) if has_report(p)]


def updated_document(text: str, reports: list[Report], records_dir: str | Path,
                     unrecorded: str | Path | None, name: str = "document") -> str:
    """``text`` with each report's block and, where it has the summary markers, the summary
    block rebuilt from the records."""
    for report in reports:
        text = with_block(text, report_markdown(report, records_dir), name, *markers(report))
    if any(m in text for m in SUMMARY_MARKERS):
        text = with_block(text, summary_markdown(records_dir, unrecorded,
                                                 reports_beside(r.grid for r in reports)),
                          name, *SUMMARY_MARKERS)
    return text


def add_parser(sub) -> None:
    r = sub.add_parser("report", help="the report of grids with a [report] table, from their "
                                      "records (docs/sweeps.md)")
    r.add_argument("grids", nargs="+", help="grid files with a [report] table")
    r.add_argument("--records", default=DEFAULT_RECORDS,
                   help=f"the records folder (default {DEFAULT_RECORDS})")
    r.add_argument("--update", metavar="FILE", default=None,
                   help="rewrite each grid's block (between its markers) and the summary block "
                        "of FILE instead of printing")
    r.add_argument("--unrecorded", default=None,
                   help="TOML list of reported runs without a record, for the summary block "
                        "(default: unrecorded.toml beside the records folder, if present)")
    r.add_argument("--check-equivalence", action="store_true",
                   help="accept this checkout's training code for the grid when it reproduces "
                        "the grid's pinned run bit for bit (refgs.analysis.equivalence)")
    r.add_argument("--reference-code", metavar="DIR", default=None,
                   help="with --check-equivalence: a checkout of accepted code, to pin the run "
                        "on a CPU level that has no pinned digest yet")


def run(args) -> None:
    reports = [load_report(g) for g in args.grids]
    if args.check_equivalence:
        from .equivalence import check_equivalence

        for report in reports:
            print(check_equivalence(report, args.reference_code))
        return
    if args.update:
        path = Path(args.update)
        if not path.is_file():
            raise ConfigError(f"--update: {path} not found")
        unrecorded = args.unrecorded or default_unrecorded(args.records)
        text = updated_document(path.read_text(encoding="utf-8"), reports, args.records,
                                unrecorded, str(path))
        atomic_write_text(path, text)
        return
    sys.stdout.write("\n".join(report_markdown(r, args.records) for r in reports))


__all__ = ["report_markdown", "load_runs", "all_runs", "report_run", "updated_document",
           "split_document", "with_block", "reports_beside", "markers", "SUMMARY_MARKERS",
           "add_parser", "run"]
