"""A grid's flatness table: robustness to SAP position perturbations over training seeds (FM-12,
the paper's perturbation figure), built from flatness records of the grid's runs (a report's
``[report.flatness]`` table, refgs.analysis.report).

A flatness record (``refgs record`` of a ``refgs flatness`` folder) holds one curve per run: PSNR
on the training and the test views at each gamma, each the mean over perturbation seeds.  A curve
belongs to the report when its ``run`` entry names one of the report's records.  Per (scene,
views) of the table's groups and method the table gives, over the training seeds, the mean PSNR
at gamma = 0 and at the largest gamma, and the *drop* between them (per run: PSNR at 0 minus PSNR
at the largest gamma; a flatter minimum drops less) as mean with its Student-t 95 % CI over the
seeds; then each comparison's drop difference, paired by training seed.  Only curves of the
analysis settings (``refgs flatness --settings flatness``: p = 1, alpha = 1, no clamp) count.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .report_spec import FLATNESS_SETTINGS
from .report_tables import ReportRun, diff_cells, head, percent, prose, row
from .stats import CONFIDENCE, paired_stats
from .tables import read_run_json

FLATNESS_FILE = "flatness.json"
SPLITS = ("test", "train")
NOT_YET = "not analysed yet"


def load_curves(records_dir: str | Path, runs: list[ReportRun]) -> dict:
    """{(scene, views, method, seed): (flatness record id, curve)} of the runs' curves
    in the flatness records of ``records_dir``; ConfigError naming both records when one run
    has two curves, or naming the record when a curve lacks its run or gammas."""
    by_name = {r.record: r for r in runs}
    out: dict = {}
    for folder in sorted(p for p in Path(records_dir).iterdir() if p.is_dir()):
        if not (folder / FLATNESS_FILE).is_file():
            continue
        data = read_run_json(folder / FLATNESS_FILE)
        for label, curve in (data.get("runs") or {}).items():
            run = curve.get("run") if isinstance(curve, dict) else None
            if not isinstance(run, dict) or run.get("name") not in by_name:
                continue                          # not one of the report's runs
            if curve.get("settings") != FLATNESS_SETTINGS:
                continue
            if not all(k in curve for k in ("gammas", *SPLITS)):
                raise ConfigError(f"{folder.name}/{FLATNESS_FILE}: curve {label!r} lacks gammas "
                                  "or train/test")
            r = by_name[run["name"]]
            key = (r.scene, r.views, r.method, r.seed)
            if key in out:
                raise ConfigError(f"{folder.name}/{FLATNESS_FILE}: {run['name']} also has a curve "
                                  f"in {out[key][0]}")
            out[key] = (folder.name, curve)
    return out


def drop(curve: dict, split: str) -> float:
    """PSNR at gamma = 0 minus PSNR at the largest gamma, on ``split``'s views."""
    m = curve[split]["mean"]
    return float(m[0] - m[-1])


def _mean(values: list) -> str:
    return f"{np.mean(values):.2f}"


def flatness_markdown(records_dir: str | Path, report, runs: list[ReportRun]) -> str:
    """The flatness section of a report (module docstring) over ``report.flatness_groups``."""
    curves = load_curves(records_dir, runs)
    titles = ["scene", "views", "method", "n"]
    for split in SPLITS:
        titles += [f"{split}, γ = 0", f"{split}, largest γ",
                   f"{split} drop [{percent(CONFIDENCE)} CI]"]
    lines = head(titles + ["flatness records"])
    diffs = head(["scene", "views", "difference", "pairs",
                  *(t for s in SPLITS for t in (f"Δ {s} drop [{percent(CONFIDENCE)} CI]",
                                                f"p ({s})"))])
    for scene, views in report.flatness_groups:
        for method in report.methods:
            got = [curves[(scene, views, method, s)] for s in report.seeds
                   if (scene, views, method, s) in curves]
            cells = [scene, str(views), method, str(len(got))]
            if not got:
                lines.append(row(cells + [NOT_YET] + [""] * 6))
                continue
            gmax = got[0][1]["gammas"][-1]
            for split in SPLITS:
                cells += [_mean([c[split]["mean"][0] for _, c in got]),
                          f"{_mean([c[split]['mean'][-1] for _, c in got])} (γ = {gmax:g})",
                          diff_cells(paired_stats([drop(c, split) for _, c in got]), 2)[0]]
            cells.append(", ".join(f"`{r}`" for r in dict.fromkeys(r for r, _ in got)))
            lines.append(row(cells))
        for method, base in report.comparisons:
            pairs = [(curves[(scene, views, method, s)][1], curves[(scene, views, base, s)][1])
                     for s in report.seeds
                     if (scene, views, method, s) in curves and (scene, views, base, s) in curves]
            cells = [scene, str(views), f"{report.display(method)} − {report.display(base)}",
                     str(len(pairs))]
            if not pairs:
                diffs.append(row(cells + ["no pairs yet", "", "", ""]))
                continue
            for split in SPLITS:
                cells += diff_cells(paired_stats([drop(a, split) - drop(b, split)
                                                  for a, b in pairs]), 2)[:2]
            diffs.append(row(cells))
    names = " and ".join(f"{s} {v}-view" for s, v in report.flatness_groups)
    firsts = {a for a, _ in report.comparisons}
    who = report.display(firsts.pop()) if len(firsts) == 1 else "each method"
    intro = (f"PSNR of the final models of {names} under "
             "Scale-Adaptive Perturbation of every Gaussian's position (`refgs flatness`, p = 1, "
             "α = 1, no clamp; each run's value the mean over its perturbation seeds), averaged "
             "over the training seeds; the drop is γ = 0 minus the largest γ, per run, with its "
             f"{percent(CONFIDENCE)} Student-t CI over the seeds (a flatter minimum drops less). "
             f"Then {who}'s drop minus each baseline's, paired by training seed (negative: {who} "
             "is flatter).")
    return "\n".join(["### Flatness over training seeds", "", prose(intro), "", *lines, "",
                      *diffs])


__all__ = ["load_curves", "drop", "flatness_markdown"]
