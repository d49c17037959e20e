"""The summary tables of docs/results.md, built from the committed records (FM-13, FM-15).

    python -m refgs.analysis.summary results/records [--unrecorded FILE] [--main | --followups]
                                     [--update docs/results.md]

Reads every record folder of ``results/records/`` (``refgs record``): a run's ``config.json``
(scene, views, iterations, method and its parameters, seed) and ``metrics.json`` (the test-view
means), or a flatness analysis' ``flatness.json`` (FM-12).  Runs are grouped into experiment
families (``FAMILIES``: the fern 3-view methods over seeds, more views, bonsai, the plug-in, the
ablations, anything else) and, within a family, by scene, views and method label
(``refgs.analysis.tables.method_label``: the method, ``+fm`` for the plug-in, the non-default
method parameters in brackets).  Each row gives the seeds, PSNR / SSIM / LPIPS-VGG as mean +-
sample standard deviation over the seeds (a single value for one seed) and the record ids; the
ablation rows add their difference from the plain ``fm`` record of the same seed.

Runs that were reported before records existed are listed, without numbers, in a TOML file
(``unrecorded.toml`` beside the records folder by default) as ``[[run]]`` tables with ``scene``,
``views``, ``iters``, ``method`` (a method label), ``seeds`` (text) and ``note``; each becomes a
row marked "no record".  Every number printed comes from a record.

The records of the main campaign (``refgs.analysis.campaign``: made by the grid
experiments/paper_main.toml) are left out of the families; they make their own block
(``main_markdown``: ``campaign.campaign_markdown`` and the flatness over training seeds of
``campaign_flatness.flatness_markdown``), printed with ``--main``; so do those of its
follow-ups (``campaign_followups``: the grid experiments/paper_followups.toml), printed with
``--followups``.

The output is Markdown; in docs/results.md the summary sits between ``BEGIN_MARKER`` and
``END_MARKER``, the campaign block between ``MAIN_BEGIN`` and ``MAIN_END``, the follow-ups'
between ``FOLLOWUPS_BEGIN`` and ``FOLLOWUPS_END``, and ``--update FILE`` rewrites the blocks in
place (atomically; the campaign and follow-up blocks only where FILE has their markers).
tests/test_results_doc.py checks that the document's blocks are exactly this output.
"""
from __future__ import annotations

import argparse
import json
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError, RefgsError
from ..io.atomic import atomic_write_text
from .campaign import (CAMPAIGN_SOURCE_HASHES, campaign_markdown, load_campaign,
                       made_by_campaign, prose)
from .campaign_compute import compute_markdown
from .campaign_followups import FOLLOWUPS_GRID, followups_markdown
from .campaign_flatness import flatness_markdown
from .campaign_paper import paper_markdown
from .tables import method_label

BEGIN_MARKER = "<!-- summary:begin -->"
END_MARKER = "<!-- summary:end -->"
MAIN_BEGIN = "<!-- main:begin -->"
MAIN_END = "<!-- main:end -->"
FOLLOWUPS_BEGIN = "<!-- followups:begin -->"
FOLLOWUPS_END = "<!-- followups:end -->"
#: The paper's protocol length (the DropGaussian settings: T = 10,000 iterations); runs of another
#: length carry "T = ..." in their method cell.
PROTOCOL_ITERS = 10_000
#: (metrics.json key, column title, decimals shown): the paper's three metrics.
METRICS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("lpips_vgg", "LPIPS-VGG", 3))
#: The name of the list of unrecorded runs, looked for beside the records folder.
UNRECORDED_FILE = "unrecorded.toml"
NO_RECORD = "no record"


@dataclass(frozen=True)
class Run:
    """One recorded training run."""

    record: str
    scene: str
    views: int
    iters: int
    label: str
    seed: int
    metrics: dict
    #: made by the campaign's training code (campaign.CAMPAIGN_SOURCE_HASHES) outside its grid
    campaign_code: bool = False


@dataclass(frozen=True)
class Unrecorded:
    """A reported run whose folder was lost before records existed (no numbers kept here)."""

    scene: str
    views: int
    iters: int
    label: str
    seeds: str
    note: str


@dataclass(frozen=True)
class Family:
    """A table: ``select(scene, views, iters, label)`` picks its rows; ``baseline`` (a method
    label) adds the difference of each row from that label's record of the same seed."""

    title: str
    select: Callable[[str, int, int, str], bool]
    baseline: str | None = None


def plain(label: str) -> bool:
    """A method as published: no plug-in, no changed parameter."""
    return "+" not in label and "[" not in label


#: The family of the runs the campaign's training code made outside its grid (e.g. the float64
#: control of docs/performance.md): listed apart, not mixed with older code's runs of the same
#: settings.
CAMPAIGN_CODE_FAMILY = Family("Made by the campaign's code, outside its grid",
                              lambda s, v, t, m: False)
#: The families, in the order of the document; a run goes to the first that selects it, and
#: "Other runs" catches whatever none of the others takes.
FAMILIES = (
    CAMPAIGN_CODE_FAMILY,
    Family("Fern, 3 views: the three methods over seeds",
           lambda s, v, t, m: s == "fern" and v == 3 and t == PROTOCOL_ITERS and plain(m)),
    Family("Fern, 6 and 9 views",
           lambda s, v, t, m: s == "fern" and v in (6, 9) and t == PROTOCOL_ITERS and plain(m)),
    Family("Bonsai, 12 views",
           lambda s, v, t, m: s == "bonsai" and v == 12 and t == PROTOCOL_ITERS and plain(m)),
    Family("FM as a plug-in on DropGaussian",
           lambda s, v, t, m: "+fm" in m and t == PROTOCOL_ITERS),
    Family("Ablations of FM (difference from the fm record of the same seed)",
           lambda s, v, t, m: m.startswith("fm[") and t == PROTOCOL_ITERS, baseline="fm"),
    Family("Other runs", lambda s, v, t, m: True),
)


# --- reading --------------------------------------------------------------------------------
def read_json(path: Path) -> dict:
    """A JSON object from ``path``; ConfigError naming the file if it is missing or invalid."""
    if not path.is_file():
        raise ConfigError(f"{path}: not found (expected a record written by refgs record)")
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object")
    return data


def load_run(folder: Path, config: dict | None = None) -> Run:
    """The Run of a record folder holding config.json (or its content ``config``) and
    metrics.json."""
    config = read_json(folder / "config.json") if config is None else config
    settings = config.get("settings")
    metrics = read_json(folder / "metrics.json")
    if not isinstance(settings, dict):
        raise ConfigError(f"{folder / 'config.json'}: no 'settings' object")
    try:
        campaign_code = (config.get("provenance") or {}).get("source_hash") \
            in CAMPAIGN_SOURCE_HASHES
        label = method_label(settings)
        if campaign_code:                   # these rows compare training settings: name the dtype
            label = f"{label}, {settings['dtype']}"
        return Run(folder.name, Path(settings["scene"]).name, int(settings["views"]),
                   int(settings["iters"]), label, int(settings["seed"]), metrics, campaign_code)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{folder / 'config.json'}: settings lack scene, views, iters, seed or "
                          f"dtype ({exc})") from None


def load_records(records_dir: str | Path) -> tuple[list[Run], dict[str, dict]]:
    """(runs, {record id: flatness.json}) of every folder of ``records_dir`` except the records
    of the main campaign and its follow-ups; folders that are neither are refused (ConfigError
    naming the folder)."""
    records_dir = Path(records_dir)
    if not records_dir.is_dir():
        raise ConfigError(f"{records_dir}: not a folder (expected results/records)")
    runs, flatness = [], {}
    for folder in sorted(p for p in records_dir.iterdir() if p.is_dir()):
        if (folder / "config.json").is_file():
            config = read_json(folder / "config.json")
            if not (made_by_campaign(config) or made_by_campaign(config, FOLLOWUPS_GRID)):
                runs.append(load_run(folder, config))
        elif (folder / "flatness.json").is_file():
            flatness[folder.name] = read_json(folder / "flatness.json")
        else:
            raise ConfigError(f"{folder}: neither config.json nor flatness.json (not a record)")
    return runs, flatness


def load_unrecorded(path: str | Path) -> list[Unrecorded]:
    """The ``[[run]]`` tables of the TOML list of unrecorded runs; ConfigError naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: not a readable TOML file ({exc})") from None
    out = []
    for k, entry in enumerate(data.get("run", [])):
        try:
            out.append(Unrecorded(str(entry["scene"]), int(entry["views"]), int(entry["iters"]),
                                  str(entry["method"]), str(entry["seeds"]), str(entry["note"])))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{path}: run {k + 1}: expected scene, views, iters, method, seeds "
                              f"and note ({exc})") from None
    return out


# --- formatting -----------------------------------------------------------------------------
def mean_std_cell(values: list, decimals: int) -> str:
    """``m ± s`` (sample std) for several values, the value for one, ``n/a`` if any is missing."""
    if any(v is None for v in values):
        return "n/a"
    a = np.asarray(values, np.float64)
    if a.size == 1:
        return f"{a[0]:.{decimals}f}"
    return f"{a.mean():.{decimals}f} ± {a.std(ddof=1):.{decimals}f}"


def delta_cell(value, base, decimals: int) -> str:
    if value is None or base is None:
        return "n/a"
    return f"{value - base:+.{decimals}f}"


def method_cell(label: str, iters: int) -> str:
    return label if iters == PROTOCOL_ITERS else f"{label}, T = {iters}"


def family_of(scene: str, views: int, iters: int, label: str) -> int:
    return next(k for k, f in enumerate(FAMILIES) if f.select(scene, views, iters, label))


def family_table(family: Family, runs: list[Run], unrecorded: list[Unrecorded],
                 all_runs: list[Run]) -> str:
    """The Markdown table of one family (rows sorted by scene, views, iterations, label)."""
    head = ["scene", "views", "method", "seeds", *(t for _, t, _ in METRICS)]
    if family.baseline:
        head += [f"Δ {t}" for _, t, _ in METRICS] + ["vs"]
    head.append("records")
    groups: dict = {}
    for r in runs:
        groups.setdefault((r.scene, r.views, r.iters, r.label), []).append(r)
    rows = []
    for (scene, views, iters, label), rs in groups.items():
        rs = sorted(rs, key=lambda r: r.seed)
        cells = [scene, str(views), method_cell(label, iters), ", ".join(str(r.seed) for r in rs)]
        cells += [mean_std_cell([r.metrics.get(k) for r in rs], d) for k, _, d in METRICS]
        if family.baseline:
            cells += baseline_cells(family.baseline, rs, all_runs)
        cells.append(", ".join(f"`{r.record}`" for r in rs))
        rows.append(((scene, views, iters, label, 0), cells))
    for u in unrecorded:
        cells = [u.scene, str(u.views), method_cell(u.label, u.iters), u.seeds]
        cells += [NO_RECORD] + [""] * (len(METRICS) - 1)
        if family.baseline:
            cells += [""] * (len(METRICS) + 1)
        cells.append(u.note)
        rows.append(((u.scene, u.views, u.iters, u.label, 1), cells))
    rows.sort(key=lambda kc: kc[0])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(c) + " |" for _, c in rows]
    return "\n".join(lines)


def baseline_cells(baseline: str, rs: list[Run], all_runs: list[Run]) -> list[str]:
    """Δ per metric of the rows' mean from the mean of the baseline records of the same scene,
    views, iterations and seeds (paired by seed), and the baseline record ids."""
    r0 = rs[0]
    by_seed = {r.seed: r for r in all_runs if (r.scene, r.views, r.iters, r.label)
               == (r0.scene, r0.views, r0.iters, baseline)}
    base = [by_seed.get(r.seed) for r in rs]
    if any(b is None for b in base):
        return ["n/a"] * len(METRICS) + [f"no {baseline} record of seed(s) "
                                         + ", ".join(str(r.seed) for r, b in zip(rs, base) if b is None)]
    cells = []
    for key, _, d in METRICS:
        vals, refs = [r.metrics.get(key) for r in rs], [b.metrics.get(key) for b in base]
        ok = all(v is not None for v in vals + refs)
        cells.append(delta_cell(float(np.mean(vals)) if ok else None,
                                float(np.mean(refs)) if ok else None, d))
    return cells + [", ".join(f"`{b.record}`" for b in base)]


def largest_drop(gammas: list, means: list) -> str:
    """The largest fall of a PSNR curve below its gamma = 0 value, with the gamma it falls at
    (the curves of sharp minima need not be monotone in gamma)."""
    k = int(np.argmax([means[0] - m for m in means]))
    return f"{means[0] - means[k]:.2f} (γ = {gammas[k]:g})"


def flatness_table(flatness: dict[str, dict]) -> str:
    """PSNR on the test and the training views without perturbation (gamma = 0), at the largest
    gamma (mean ± std over the perturbation seeds) and the largest drop, for every run of every
    flatness record (FM-12)."""
    head = ["run", "perturbation seeds", "test, γ = 0", "test, largest γ", "largest test drop",
            "train, γ = 0", "train, largest γ", "largest train drop", "record"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for record, data in sorted(flatness.items()):
        runs = data.get("runs")
        if not isinstance(runs, dict):
            raise ConfigError(f"{record}/flatness.json: no 'runs' object")
        for name, r in runs.items():
            try:
                g, test, train = r["gammas"], r["test"], r["train"]
                cells = [name.split(" ")[0], str(len(test["all"][-1]))]
                for views in (test, train):
                    m, sd = views["mean"], views["std"]
                    cells += [f"{m[0]:.2f}", f"{m[-1]:.2f} ± {sd[-1]:.2f} (γ = {g[-1]:g})",
                              largest_drop(g, m)]
                cells.append(f"`{record}`")
            except (KeyError, IndexError, TypeError) as exc:
                raise ConfigError(f"{record}/flatness.json: run {name!r} lacks gammas or "
                                  f"test/train mean, std, all ({exc})") from None
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary_markdown(records_dir: str | Path, unrecorded: str | Path | None = None) -> str:
    """The Markdown of every family table (families without rows are left out) and the
    flatness table.  ``unrecorded``: the TOML list of unrecorded runs, or None for none."""
    runs, flatness = load_records(records_dir)
    missing = load_unrecorded(unrecorded) if unrecorded is not None else []
    per_family = [([], []) for _ in FAMILIES]
    for r in runs:
        k = (FAMILIES.index(CAMPAIGN_CODE_FAMILY) if r.campaign_code
             else family_of(r.scene, r.views, r.iters, r.label))
        per_family[k][0].append(r)
    for u in missing:
        per_family[family_of(u.scene, u.views, u.iters, u.label)][1].append(u)
    parts = []
    for family, (rs, us) in zip(FAMILIES, per_family):
        if rs or us:
            parts.append(f"### {family.title}\n\n{family_table(family, rs, us, runs)}\n")
    if flatness:
        parts.append("### Flatness of the final models (SAP at p = 1, α = 1, no clamp)\n\n"
                     f"{flatness_table(flatness)}\n")
    return "\n".join(parts)


# --- the document ---------------------------------------------------------------------------
def split_document(text: str, name: str = "document", begin: str = BEGIN_MARKER,
                   end: str = END_MARKER) -> tuple[str, str, str]:
    """(before, block, after) around the one ``begin`` ... ``end`` pair (the summary's by
    default); ConfigError naming ``name`` if the markers are missing, repeated or out of order."""
    if text.count(begin) != 1 or text.count(end) != 1:
        raise ConfigError(f"{name}: expected one {begin} and one {end} line")
    before, rest = text.split(begin)
    if end not in rest:
        raise ConfigError(f"{name}: {end} comes before {begin}")
    block, after = rest.split(end)
    return before + begin, block, end + after


def with_block(text: str, markdown: str, name: str = "document", begin: str = BEGIN_MARKER,
               end: str = END_MARKER) -> str:
    """``text`` with its ``begin`` ... ``end`` block replaced by ``markdown`` (blank line on each
    side)."""
    before, _, after = split_document(text, name, begin, end)
    return f"{before}\n\n{markdown.strip()}\n\n{after}"


PAPER_HEADING = "### Beside the paper"
PAPER_PROSE = ("The paper reports dataset means; fern and bonsai are one scene of each of its "
               "datasets, desk and cup have no counterpart. Each cell: ours (mean over our "
               "seeds) / the paper's; the differences are of means (their paired CIs: above).")


def main_markdown(records_dir: str | Path) -> str:
    """The campaign block: the main tables (refgs.analysis.campaign), the paper's numbers
    beside ours (refgs.analysis.campaign_paper), the flatness over training seeds
    (refgs.analysis.campaign_flatness) and what the campaign cost
    (refgs.analysis.campaign_compute)."""
    runs = load_campaign(records_dir)
    return "\n".join([campaign_markdown(records_dir).rstrip(), "", PAPER_HEADING, "",
                      prose(PAPER_PROSE), "", paper_markdown(runs), "",
                      flatness_markdown(records_dir, runs).rstrip(), "",
                      compute_markdown(records_dir, runs)])


def updated_document(text: str, records_dir: str | Path, unrecorded: str | Path | None,
                     name: str = "document") -> str:
    """``text`` with its summary block, its campaign block where it has MAIN_BEGIN or MAIN_END
    and its follow-ups' block where it has FOLLOWUPS_BEGIN or FOLLOWUPS_END, rebuilt from the
    records."""
    text = with_block(text, summary_markdown(records_dir, unrecorded), name)
    if MAIN_BEGIN in text or MAIN_END in text:
        text = with_block(text, main_markdown(records_dir), name, MAIN_BEGIN, MAIN_END)
    if FOLLOWUPS_BEGIN in text or FOLLOWUPS_END in text:
        text = with_block(text, followups_markdown(records_dir), name, FOLLOWUPS_BEGIN,
                          FOLLOWUPS_END)
    return text


def default_unrecorded(records_dir: str | Path) -> Path | None:
    path = Path(records_dir).absolute().parent / UNRECORDED_FILE
    return path if path.is_file() else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m refgs.analysis.summary",
                                 description="print the summary tables of the recorded runs")
    ap.add_argument("records", help="the records folder (results/records)")
    ap.add_argument("--unrecorded", default=None,
                    help=f"TOML list of reported runs without a record (default: {UNRECORDED_FILE} "
                         "beside the records folder, if present)")
    ap.add_argument("--main", action="store_true",
                    help="print the main campaign's block instead of the summary")
    ap.add_argument("--followups", action="store_true",
                    help="print the follow-ups' block (experiments/paper_followups.toml) instead")
    ap.add_argument("--update", metavar="FILE", default=None,
                    help=f"rewrite the blocks between {BEGIN_MARKER} and {END_MARKER} and (where "
                         f"present) {MAIN_BEGIN} and {MAIN_END}, {FOLLOWUPS_BEGIN} and "
                         f"{FOLLOWUPS_END} of FILE instead of printing")
    args = ap.parse_args(argv)
    try:
        unrecorded = args.unrecorded or default_unrecorded(args.records)
        if args.update:
            path = Path(args.update)
            if not path.is_file():
                raise ConfigError(f"--update: {path} not found")
            text = path.read_text(encoding="utf-8")
            atomic_write_text(path, updated_document(text, args.records, unrecorded, str(path)))
        elif args.main:
            sys.stdout.write(main_markdown(args.records))
        elif args.followups:
            sys.stdout.write(followups_markdown(args.records))
        else:
            sys.stdout.write(summary_markdown(args.records, unrecorded))
    except RefgsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


__all__ = ["summary_markdown", "load_records", "load_unrecorded", "split_document", "with_block",
           "updated_document", "main_markdown", "default_unrecorded", "FAMILIES", "BEGIN_MARKER", "END_MARKER",
           "MAIN_BEGIN", "MAIN_END", "FOLLOWUPS_BEGIN", "FOLLOWUPS_END", "main"]

if __name__ == "__main__":
    sys.exit(main())
