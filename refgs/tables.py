"""``refgs table``: runs aggregated into the paper's kind of table (FM-13).

    refgs table RUN_DIR [RUN_DIR ...] [--metrics psnr ssim lpips_vgg] [--baseline LABEL] [--out DIR]

Each run directory contributes its ``config.json`` (scene, number of views, method and method
parameters, seed) and ``metrics.json`` (the test-view means).  Rows are grouped by scene, views
and method label -- the method name, ``+fm`` for the plug-in, and every method parameter that
differs from its default in brackets (``fm[perturb=rotation]``) -- and reported as mean +-
standard deviation over seeds (sample std, ddof 1; 0 for one seed), then, per views and method,
over scenes (mean of the per-scene means +- their std).  With ``--baseline LABEL`` (e.g. ``fm``
for an ablation table) every row also gets, per metric, the difference of its mean from the mean
of the baseline row of the same scene and views (the sign convention of the paper's comparisons:
row minus baseline).  Printed as Markdown and written as ``table.csv``, ``table.md`` and
``table.png``: one panel per metric, a point per (scene, views, method) row with its seed std as
the error bar -- with ``--baseline``, bars of the differences from the baseline, coloured by
whether the row is better or worse on that metric (``LOWER_IS_BETTER``).
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .errors import ConfigError
from .io.atomic import atomic_write_text

DEFAULT_METRICS = ("psnr", "ssim", "lpips_vgg")
#: Metrics where a smaller value is better (LPIPS is a distance); the others (PSNR, SSIM) are
#: better when larger.  Used only to colour the differences in ``table.png``.
LOWER_IS_BETTER = ("lpips_vgg", "lpips_vgg_official", "lpips_alex")


def method_label(settings: dict) -> str:
    """Method name, ``+fm`` for the plug-in, and the non-default method parameters."""
    from .methods.dropgaussian import R_MAX
    from .methods.training import FlatMinimaConfig

    params = dict(settings.get("method_params") or {})
    name = settings.get("method", "3dgs")
    fm = params.pop("fm", False)
    label = name + ("+fm" if fm and name != "fm" else "")
    defaults = asdict(FlatMinimaConfig())
    defaults["r_max"] = R_MAX
    if params.get("noise", defaults["noise"]) != "iso_fixed":
        # the fixed sigma only applies to "iso_fixed" noise (runs of refgs 0.1.0 before the
        # default became None record 0.0 here)
        params.pop("noise_fixed_sigma", None)
    diff = [f"{k}={params[k]}" for k in sorted(params) if k in defaults and params[k] != defaults[k]]
    return label + (f"[{','.join(diff)}]" if diff else "")


def read_run_json(path: Path) -> dict:
    """One JSON file of a run directory; ConfigError naming the file if missing or invalid."""
    if not path.is_file():
        raise ConfigError(f"{path}: not found (is {path.parent} a finished refgs run? "
                          f"finish it with refgs train --resume {path.parent})")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None


def load_run(run_dir: str | Path) -> dict:
    """scene, views, label, seed and metrics of a finished run; ConfigError naming the file."""
    run_dir = Path(run_dir)
    config = read_run_json(run_dir / "config.json")
    metrics = read_run_json(run_dir / "metrics.json")
    s = config.get("settings", {})
    return {"run": str(run_dir), "scene": Path(s.get("scene", "?")).name, "views": s.get("views"),
            "label": method_label(s), "seed": s.get("seed"), "metrics": metrics}


def _mean_std(values) -> tuple[float, float]:
    a = np.asarray(values, np.float64)
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0


def aggregate(runs: list[dict], metrics=DEFAULT_METRICS, baseline: str | None = None) -> dict:
    """{"per_scene": [...], "over_scenes": [...]} rows with mean/std/n per metric.

    ``baseline``: a method label; each row then has ``row["delta"][metric]`` = its mean minus the
    baseline row's mean at the same scene and views (None where either is missing).
    """
    seen = {}
    for r in runs:
        key = (r["scene"], r["views"], r["label"], r["seed"])
        if key in seen:
            raise ConfigError(f"{r['run']}: same scene, views, method and seed as {seen[key]}")
        seen[key] = r["run"]
    groups: dict = {}
    for r in runs:
        groups.setdefault((r["scene"], r["views"], r["label"]), []).append(r)
    per_scene = []
    for (scene, views, label), rs in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1] or 0,
                                                                              kv[0][2])):
        row = {"scene": scene, "views": views, "method": label, "seeds": sorted(r["seed"] for r in rs)}
        for m in metrics:
            vals = [r["metrics"].get(m) for r in rs]
            if any(v is None for v in vals):
                row[m] = None
            else:
                row[m] = dict(zip(("mean", "std"), _mean_std(vals)), n=len(vals))
        per_scene.append(row)
    over: dict = {}
    for row in per_scene:
        over.setdefault((row["views"], row["method"]), []).append(row)
    over_rows = []
    for (views, label), rows in sorted(over.items(), key=lambda kv: (kv[0][0] or 0, kv[0][1])):
        row = {"views": views, "method": label, "scenes": [r["scene"] for r in rows]}
        for m in metrics:
            means = [r[m]["mean"] for r in rows if r[m] is not None]
            row[m] = (dict(zip(("mean", "std"), _mean_std(means)), n=len(means))
                      if len(means) == len(rows) else None)
        over_rows.append(row)
    table = {"metrics": list(metrics), "per_scene": per_scene, "over_scenes": over_rows,
             "baseline": baseline}
    if baseline is not None:
        _add_deltas(table, baseline)
    return table


def _add_deltas(table: dict, baseline: str) -> None:
    """row["delta"] against the baseline row of the same (scene,) views; ConfigError if absent."""
    labels = sorted({r["method"] for r in table["per_scene"]})
    if baseline not in labels:
        raise ConfigError(f"--baseline {baseline!r}: no run has this method label; "
                          f"the runs have {', '.join(labels)}")
    for level, key in (("per_scene", ("scene", "views")), ("over_scenes", ("views",))):
        base = {tuple(r[k] for k in key): r for r in table[level] if r["method"] == baseline}
        for r in table[level]:
            b = base.get(tuple(r[k] for k in key))
            r["delta"] = {m: (None if b is None or r[m] is None or b[m] is None
                              else r[m]["mean"] - b[m]["mean"]) for m in table["metrics"]}


def _cell(v, digits: int) -> str:
    return "-" if v is None else f"{v['mean']:.{digits}f} ± {v['std']:.{digits}f}"


def _delta_cell(d, digits: int) -> str:
    return "-" if d is None else f"{d:+.{digits}f}"


def markdown(table: dict) -> str:
    ms = table["metrics"]
    digits = {m: (2 if m == "psnr" else 3) for m in ms}
    base = table.get("baseline")
    head = " | ".join(ms) + (" | " + " | ".join(f"Δ{m} vs {base}" for m in ms) if base else "")
    rule = "---|" * (len(ms) * (2 if base else 1))

    def cells(r):
        out = [_cell(r[m], digits[m]) for m in ms]
        if base:
            out += [_delta_cell(r["delta"][m], digits[m]) for m in ms]
        return " | ".join(out)

    lines = ["| scene | views | method | seeds | " + head + " |", "|---|---|---|---|" + rule]
    for r in table["per_scene"]:
        lines.append(f"| {r['scene']} | {r['views']} | {r['method']} | {len(r['seeds'])} | {cells(r)} |")
    lines += ["", "| views | method | scenes | " + head + " |", "|---|---|---|" + rule]
    for r in table["over_scenes"]:
        lines.append(f"| {r['views']} | {r['method']} | {len(r['scenes'])} | {cells(r)} |")
    return "\n".join(lines) + "\n"


def _csv(table: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    ms = table["metrics"]
    base = table.get("baseline")
    w.writerow(["level", "scene", "views", "method", "n"] + [f"{m}_{s}" for m in ms for s in ("mean", "std")]
               + ([f"{m}_delta_vs_{base}" for m in ms] if base else []))
    for level, rows in (("scene", table["per_scene"]), ("over_scenes", table["over_scenes"])):
        for r in rows:
            n = len(r.get("seeds", r.get("scenes", [])))
            vals = []
            for m in ms:
                vals += ["", ""] if r[m] is None else [r[m]["mean"], r[m]["std"]]
            if base:
                vals += ["" if r["delta"][m] is None else r["delta"][m] for m in ms]
            w.writerow([level, r.get("scene", "all"), r["views"], r["method"], n] + vals)
    return buf.getvalue()


def plot(table: dict, path: Path) -> None:
    """``table.png``: per metric, one point per per-scene row (mean, error bar the seed std); with
    a baseline, a bar per row, its difference from the baseline, green where the row is better on
    the metric, red where worse.  Rows without the metric are left out of its panel."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io.atomic import atomic_path

    ms, base, rows = table["metrics"], table.get("baseline"), table["per_scene"]
    labels = [f"{r['scene']} {r['views']}v {r['method']} (n={len(r['seeds'])})" for r in rows]
    fig, axes = plt.subplots(1, len(ms), figsize=(3.2 * len(ms) + 3.0, 0.35 * len(rows) + 1.4),
                             sharey=True, squeeze=False)
    y = np.arange(len(rows))
    for ax, m in zip(axes[0], ms):
        ok = [i for i, r in enumerate(rows) if r[m] is not None and (not base or r["delta"][m] is not None)]
        std = np.array([rows[i][m]["std"] for i in ok])
        if base:
            val = np.array([rows[i]["delta"][m] for i in ok])
            better = -val if m in LOWER_IS_BETTER else val
            colors = ["tab:green" if b > 0 else "tab:red" if b < 0 else "0.6" for b in better]
            ax.axvline(0.0, color="k", lw=0.8)
            ax.set_title(f"Δ{m} vs {base}\n({'lower' if m in LOWER_IS_BETTER else 'higher'} is better)",
                         fontsize=9)
        else:
            # points, not bars: the axis then spans the values, not 0 .. max
            val = np.array([rows[i][m]["mean"] for i in ok])
            ax.errorbar(val, y[ok], xerr=std, fmt="o", color="tab:blue", ecolor="k", capsize=3)
            ax.set_title(f"{m}\n({'lower' if m in LOWER_IS_BETTER else 'higher'} is better)", fontsize=9)
        if base:
            ax.barh(y[ok], val, xerr=std, color=colors, ecolor="k", capsize=2)
        ax.grid(axis="x", alpha=0.3)
        ax.xaxis.set_major_locator(plt.MaxNLocator(4))
    axes[0][0].set_yticks(y, labels, fontsize=8)
    axes[0][0].invert_yaxis()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


def add_parser(sub) -> None:
    t = sub.add_parser("table", help="aggregate finished runs: mean +- std over seeds and scenes")
    t.add_argument("run_dirs", nargs="+")
    t.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS))
    t.add_argument("--baseline", metavar="LABEL",
                   help="add each row's difference from this method label's row (e.g. fm)")
    t.add_argument("--out", default="table-out")


def run(args) -> dict:
    table = aggregate([load_run(r) for r in args.run_dirs], args.metrics, args.baseline)
    out = Path(args.out)
    md = markdown(table)
    atomic_write_text(out / "table.md", md)
    atomic_write_text(out / "table.csv", _csv(table))
    plot(table, out / "table.png")
    print(md, end="")
    print(f"written to {out}")
    return table


__all__ = ["aggregate", "load_run", "markdown", "method_label", "plot", "run"]
