"""The summary tables of docs/results.md: the records no reported grid claims (FM-13, FM-15).

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

The records made by a grid with a ``[report]`` table (``reports``) are left out: they make that
grid's block (refgs.analysis.report, which also writes this summary between its markers).  Runs
made outside those grids by training code a report accepts have a family of their own.
"""
from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError
from .report_spec import DEFAULT_METRICS, made_by
from .report_tables import mean_std
from .tables import method_label

#: The paper's protocol length (the DropGaussian settings: T = 10,000 iterations); runs of another
#: length carry "T = ..." in their method cell.
PROTOCOL_ITERS = 10_000
#: (metrics.json key, column title, decimals shown): the paper's three metrics.
METRICS = DEFAULT_METRICS
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
    #: made outside its grid by training code a report accepts (its ``[[report.code]]``)
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


def load_run(folder: Path, config: dict | None = None, accepted: tuple = ()) -> Run:
    """The Run of a record folder holding config.json (or its content ``config``) and
    metrics.json; ``accepted``: the code hashes of the reports' grids."""
    config = read_json(folder / "config.json") if config is None else config
    settings = config.get("settings")
    metrics = read_json(folder / "metrics.json")
    if not isinstance(settings, dict):
        raise ConfigError(f"{folder / 'config.json'}: no 'settings' object")
    try:
        campaign_code = (config.get("provenance") or {}).get("source_hash") in accepted
        label = method_label(settings)
        if campaign_code:                   # these rows compare training settings: name the dtype
            label = f"{label}, {settings['dtype']}"
        return Run(folder.name, Path(settings["scene"]).name, int(settings["views"]),
                   int(settings["iters"]), label, int(settings["seed"]), metrics, campaign_code)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{folder / 'config.json'}: settings lack scene, views, iters, seed or "
                          f"dtype ({exc})") from None


def load_records(records_dir: str | Path, reports=()) -> tuple[list[Run], dict[str, dict]]:
    """(runs, {record id: flatness.json}) of every folder of ``records_dir`` except the records
    made by the grids of ``reports`` (refgs.analysis.report_spec.Report); folders that are
    neither runs nor flatness analyses are refused (ConfigError naming the folder)."""
    records_dir = Path(records_dir)
    if not records_dir.is_dir():
        raise ConfigError(f"{records_dir}: not a folder (expected results/records)")
    runs, flatness = [], {}
    accepted = tuple(h for r in reports for h in r.code)
    for folder in sorted(p for p in records_dir.iterdir() if p.is_dir()):
        if (folder / "config.json").is_file():
            config = read_json(folder / "config.json")
            if not any(made_by(config, r) for r in reports):
                runs.append(load_run(folder, config, accepted))
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
        cells += [mean_std([r.metrics.get(k) for r in rs], d) for k, _, d in METRICS]
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


def summary_markdown(records_dir: str | Path, unrecorded: str | Path | None = None,
                     reports=()) -> str:
    """The Markdown of every family table (families without rows are left out) and the
    flatness table.  ``unrecorded``: the TOML list of unrecorded runs, or None for none;
    ``reports``: the reported grids whose records are left out (load_records)."""
    runs, flatness = load_records(records_dir, reports)
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


def default_unrecorded(records_dir: str | Path) -> Path | None:
    path = Path(records_dir).absolute().parent / UNRECORDED_FILE
    return path if path.is_file() else None


__all__ = ["summary_markdown", "load_records", "load_unrecorded", "default_unrecorded",
           "FAMILIES", "METRICS", "PROTOCOL_ITERS"]
