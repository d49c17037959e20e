"""``refgs table``: runs aggregated into the paper's kind of table (FM-13) with paired
statistics against a baseline (FM-16).

    refgs table RUN_DIR [RUN_DIR ...] [--metrics psnr ssim lpips_vgg] [--baseline LABEL] [--out DIR]

Each run directory (or record folder, FM-15) contributes its ``config.json`` (scene, number of
views, method and method parameters, seed, the other settings) and ``metrics.json`` (the
test-view means).  Rows are grouped by condition -- scene, views and the other settings
(``stats.conditions``; a setting in which the runs differ is shown beside the scene,
``fern (iters=3000)``) -- and method label -- the method name, ``+fm`` for the plug-in, and
every method parameter that differs from its default in brackets (``fm[perturb=rotation]``) --
and reported as mean +- standard deviation over seeds (sample std, ddof 1; 0 for one seed),
then, per views and method, over scenes (mean of the per-scene means +- their std).  With
``--baseline LABEL`` every row also gets, per metric, the difference of its mean from the mean of
the baseline row of the same condition (row minus baseline), and every method is compared with
the baseline seed by seed (``stats.compare``: mean paired difference, 95 % CI, paired t-test p,
Wilcoxon p, runs needed; pooled over scenes).

Printed as Markdown; ``--out`` gets ``table.md``, ``table.csv``, ``table.json`` and ``table.png``
(one panel per metric, a point per (scene, views, method) row with its seed std as the error bar;
with ``--baseline``, bars of the differences, coloured by whether the row is better or worse on
that metric, ``LOWER_IS_BETTER``) and, with ``--baseline``, ``forest.png`` (each method's paired
difference with its CI, per scene and pooled).
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_path, atomic_write_json, atomic_write_text
from .stats import (ALL_SCENES, ALPHA, CONFIDENCE, POWER, WILCOXON_MIN_PAIRS,
                    compare, conditions, excludes_zero, metric_value, setup_labels, setup_of, with_setup)

DEFAULT_METRICS = ("psnr", "ssim", "lpips_vgg")
#: Metrics where a smaller value is better (LPIPS is a distance); the others (PSNR, SSIM) are
#: better when larger.  Used only to colour the differences in ``table.png``.
LOWER_IS_BETTER = ("lpips_vgg", "lpips_vgg_official", "lpips_alex")


def method_label(settings: dict) -> str:
    """Method name, ``+fm`` for the plug-in, the non-default method parameters, and the compact
    strategy's settings (TRN-14) where the run has them."""
    from ..methods.dropgaussian import R_MAX
    from ..train.strategy import compact_label
    from ..methods.flat_minima_method import FlatMinimaConfig

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
    return label + (f"[{','.join(diff)}]" if diff else "") + compact_label(settings.get("compact"))


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
    """run, scene (folder name), views, label, seed, metrics and setup (the other settings,
    ``stats.setup_of``) of a finished run or its record; ConfigError naming the file."""
    run_dir = Path(run_dir)
    config = read_run_json(run_dir / "config.json")
    metrics = read_run_json(run_dir / "metrics.json")
    s = config.get("settings", {})
    if not isinstance(s, dict) or not isinstance(metrics, dict):
        raise ConfigError(f"{run_dir}: config.json 'settings' and metrics.json must be JSON objects")
    return {"run": str(run_dir), "scene": Path(s.get("scene", "?")).name, "views": s.get("views"),
            "label": method_label(s), "seed": s.get("seed"), "metrics": metrics,
            "setup": setup_of(s)}


def _mean_std(values) -> tuple[float, float]:
    a = np.asarray(values, np.float64)
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0


def aggregate(runs: list[dict], metrics=DEFAULT_METRICS, baseline: str | None = None) -> dict:
    """{"per_scene": [...], "over_scenes": [...]} rows with mean/std/n per metric.

    Rows are keyed by condition (``stats.conditions``: scene with any differing settings, views)
    and method label; over-scenes rows by views, settings and label, their ``scene`` being
    ``all`` (with the settings).  ``baseline``: a method label; each row then has
    ``row["delta"][metric]`` = its mean minus the baseline row's mean in the same condition (None
    where either is missing).
    """
    groups: dict = {}
    setups = {}
    for r, (scene, views), setup in zip(runs, conditions(runs), setup_labels(runs)):
        groups.setdefault((scene, views, r["label"]), []).append(r)
        setups[scene] = setup
    per_scene = []
    for (scene, views, label), rs in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1] or 0,
                                                                              kv[0][2])):
        row = {"scene": scene, "views": views, "method": label, "seeds": sorted(r["seed"] for r in rs)}
        for m in metrics:
            vals = [metric_value(r, m) for r in rs]
            if any(v is None for v in vals):
                row[m] = None
            else:
                row[m] = dict(zip(("mean", "std"), _mean_std(vals)), n=len(vals))
        per_scene.append(row)
    over: dict = {}
    for row in per_scene:
        over.setdefault((row["views"], setups[row["scene"]], row["method"]), []).append(row)
    over_rows = []
    for (views, setup, label), rows in sorted(over.items(), key=lambda kv: (kv[0][0] or 0, kv[0][1:])):
        row = {"scene": with_setup(ALL_SCENES, setup), "setup": setup, "views": views,
               "method": label, "scenes": [r["scene"] for r in rows]}
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
    """row["delta"] against the baseline row of the same scene and views; ConfigError if absent."""
    labels = sorted({r["method"] for r in table["per_scene"]})
    if baseline not in labels:
        raise ConfigError(f"--baseline {baseline!r}: no run has this method label; "
                          f"the runs have {', '.join(labels)}")
    for level, key in (("per_scene", ("scene", "views")), ("over_scenes", ("scene", "views"))):
        base = {tuple(r[k] for k in key): r for r in table[level] if r["method"] == baseline}
        for r in table[level]:
            b = base.get(tuple(r[k] for k in key))
            r["delta"] = {m: (None if b is None or r[m] is None or b[m] is None
                              else r[m]["mean"] - b[m]["mean"]) for m in table["metrics"]}


def _digits(metric: str) -> int:
    """Decimals shown: 2 for PSNR (dB), 3 for the metrics in [0, 1]."""
    return 2 if metric == "psnr" else 3


def _cell(v, digits: int) -> str:
    return "-" if v is None else f"{v['mean']:.{digits}f} ± {v['std']:.{digits}f}"


def _delta_cell(d, digits: int) -> str:
    return "-" if d is None else f"{d:+.{digits}f}"


def markdown(table: dict) -> str:
    """The mean ± std table per condition and method, then over scenes (with a baseline: the
    difference of means from the baseline's row)."""
    ms = table["metrics"]
    digits = {m: _digits(m) for m in ms}
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
        views = f"{r['views']} ({r['setup']})" if r["setup"] else r["views"]
        lines.append(f"| {views} | {r['method']} | {len(r['scenes'])} | {cells(r)} |")
    if base:
        lines += ["", f"(Mean ± sample std over seeds; Δ: the row's mean minus the {base} row's mean, "
                  "over all their seeds, unpaired; over scenes: of the per-scene means.)"]
    return "\n".join(lines) + "\n"


#: Per-metric columns of the paired statistics in table.csv (over_scenes rows: n = scenes).
PAIRED_CSV_COLUMNS = ("n_pairs", "paired_diff", "ci95_lo", "ci95_hi", "p_t", "p_wilcoxon",
                      "runs_needed")


def _paired_cells(c: dict | None) -> list:
    if c is None:
        return [""] * len(PAIRED_CSV_COLUMNS)
    ci = c.get("ci95") or ["", ""]
    return [c.get("n_pairs", c.get("n_scenes")), c["mean_diff"], ci[0], ci[1],
            "" if c["p_value"] is None else c["p_value"],
            "" if c.get("wilcoxon_p") is None else c["wilcoxon_p"],
            "" if c.get("runs_needed") is None else c["runs_needed"]]


def _csv(table: dict, comp: dict | None = None) -> str:
    """One line per per-scene and over-scenes row: mean, std (and the difference of means from
    the baseline) per metric, then with ``comp`` the paired statistics (``PAIRED_CSV_COLUMNS``)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    ms = table["metrics"]
    base = table.get("baseline")
    w.writerow(["level", "scene", "views", "method", "n"] + [f"{m}_{s}" for m in ms for s in ("mean", "std")]
               + ([f"{m}_delta_vs_{base}" for m in ms] if base else [])
               + ([f"{m}_{c}" for m in ms for c in PAIRED_CSV_COLUMNS] if comp else []))
    found = {}
    if comp:
        wil = {_ident(d): d["wilcoxon_p"] for d in comp["details"]}
        found = {_ident(c): dict(c, wilcoxon_p=wil[_ident(c)]) for c in comp["comparisons"]}
        found.update({_ident(c): c for c in comp["pooled"]})
    for level, rows in (("scene", table["per_scene"]), ("over_scenes", table["over_scenes"])):
        for r in rows:
            n = len(r.get("seeds", r.get("scenes", [])))
            vals = []
            for m in ms:
                vals += ["", ""] if r[m] is None else [r[m]["mean"], r[m]["std"]]
            if base:
                vals += ["" if r["delta"][m] is None else r["delta"][m] for m in ms]
            if comp:
                for m in ms:
                    vals += _paired_cells(found.get((r["scene"], r["views"], r["method"], m)))
            w.writerow([level, r["scene"], r["views"], r["method"], n] + vals)
    return buf.getvalue()


def _ident(c: dict) -> tuple:
    return c["scene"], c["views"], c["method"], c["metric"]


def _fmt_p(p) -> str:
    return "-" if p is None else (f"{p:.3f}" if p >= 1e-3 else f"{p:.1e}")


def _diff_cell(c: dict | None, n_row: int | None, digits: int) -> str:
    """``+0.52 [+0.31, +0.73]``, bold where the CI excludes 0; the note where there is no CI."""
    if c is None:
        return "-"
    d = f"{c['mean_diff']:+.{digits}f}"
    ci = c["ci95"]
    n = c.get("n_pairs", c.get("n_scenes"))
    text = (f"{d} ({c['note']})" if ci is None else
            f"{'**' + d + '**' if excludes_zero(ci) else d} [{ci[0]:+.{digits}f}, {ci[1]:+.{digits}f}]")
    return text + (f" (n = {n})" if n_row is not None and n != n_row and ci is not None else "")


def paired_markdown(comp: dict, metrics, baseline: str) -> str:
    """The paired comparisons as Markdown: the table a paper prints (Δ and its 95 % CI per
    metric), the same pooled over scenes, every test, and what could not be paired."""
    notes = {_ident(d): d for d in comp["details"]}
    rows: dict = {}
    for c in comp["comparisons"]:
        rows.setdefault((c["scene"], c["views"], c["method"]), {})[c["metric"]] = dict(c, **notes[_ident(c)])
    lower = [m for m in metrics if m in LOWER_IS_BETTER]
    head = " | ".join(f"Δ{m} [95 % CI]" for m in metrics)
    rule = "---|" * len(metrics)
    lines = [f"Paired differences, method − {baseline}, over the seeds both have (Student-t 95 % CI; "
             f"**bold**: the CI excludes 0" + (f"; lower is better for {', '.join(lower)}" if lower else "")
             + "):", "", "| scene | views | method | pairs | " + head + " |", "|---|---|---|---|" + rule]
    for (scene, views, method), cs in rows.items():
        n = next(iter(cs.values()))["n_pairs"]
        cells = " | ".join(_diff_cell(cs.get(m), n, _digits(m)) for m in metrics)
        lines.append(f"| {scene} | {views} | {method} | {n} | {cells} |")
    pooled: dict = {}
    for c in comp["pooled"]:
        pooled.setdefault((c["scene"], c["views"], c["method"]), {})[c["metric"]] = c
    if pooled:
        lines += ["", "Over scenes: the mean of the per-scene mean differences, Student-t 95 % CI over "
                  "scenes:", "", "| scenes | views | method | n scenes | " + head + " |",
                  "|---|---|---|---|" + rule]
        for (scene, views, method), cs in pooled.items():
            n = next(iter(cs.values()))["n_scenes"]
            cells = " | ".join(_diff_cell(cs.get(m), n, _digits(m)) for m in metrics)
            lines.append(f"| {scene} | {views} | {method} | {n} | {cells} |")
    lines += ["", f"Tests: paired t-test p; Wilcoxon signed-rank p from {WILCOXON_MIN_PAIRS} pairs; runs "
              f"needed: seeds at which the observed mean difference is detected with {POWER:.0%} power "
              f"at alpha = {ALPHA} given the observed spread:", "",
              "| scene | views | method | metric | pairs | Δ | 95 % CI | p (t) | p (Wilcoxon) "
              "| runs needed | note |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in comp["comparisons"]:
        k, d = _digits(c["metric"]), notes[_ident(c)]
        ci = "-" if c["ci95"] is None else f"[{c['ci95'][0]:+.{k}f}, {c['ci95'][1]:+.{k}f}]"
        need = "-" if c["runs_needed"] is None else c["runs_needed"]
        lines.append(f"| {c['scene']} | {c['views']} | {c['method']} | {c['metric']} | {c['n_pairs']} | "
                     f"{c['mean_diff']:+.{k}f} | {ci} | {_fmt_p(c['p_value'])} | "
                     f"{_fmt_p(d['wilcoxon_p'])} | {need} | {d['note']} |")
    if comp["unpaired"]:
        lines += ["", "Not compared:", ""]
        lines += [f"- {u['scene']} {u['views']} views, {u['method']} ({', '.join(u['metrics'])}): "
                  f"{u['reason']}" for u in comp["unpaired"]]
    return "\n".join(lines) + "\n"


def plot(table: dict, path: Path) -> None:
    """``table.png``: per metric, one point per per-scene row (mean, error bar the seed std); with
    a baseline, a bar per row, its difference from the baseline, green where the row is better on
    the metric, red where worse.  Rows without the metric are left out of its panel."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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


#: forest.png's x-axis spans the per-scene intervals, 0 and every mean, widened by this fraction
#: of the span on each side; a pooled interval reaching beyond is cut at the edge (arrow) and
#: printed (over two or three scenes a t interval can be ten times a scene's)
FOREST_MARGIN = 0.12


def forest_limits(entries: list) -> tuple[float, float]:
    """The x-limits of one forest panel (FOREST_MARGIN) from its rows (None: no row)."""
    xs = [0.0]
    for c in entries:
        if c is None:
            continue
        xs.append(c["mean_diff"])
        if c["ci95"] is not None and "n_scenes" not in c:
            xs += list(c["ci95"])
    lo, hi = min(xs), max(xs)
    pad = FOREST_MARGIN * (hi - lo) if hi > lo else 1.0
    return lo - pad, hi + pad


def forest(comp: dict, metrics, baseline: str, path: Path) -> None:
    """``forest.png``: per metric, each method's mean paired difference from the baseline with its
    95 % CI, grouped by scene, then the pooled rows (diamonds).  Green / red where the CI excludes
    0 and the method is better / worse (``LOWER_IS_BETTER``), grey otherwise; a hollow marker
    without a bar where there is no interval (one pair).  The axis spans the per-scene intervals
    (forest_limits); a wider pooled interval is cut there, with arrows and its numbers."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries: dict = {}
    for c in comp["comparisons"] + comp["pooled"]:
        entries.setdefault((c["scene"], c["views"], c["method"]), {})[c["metric"]] = c
    keys = list(entries)
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.2 * len(metrics) + 3.5, 0.35 * len(keys) + 1.6),
                             sharey=True, squeeze=False)
    y = np.arange(len(keys))
    for ax, m in zip(axes[0], metrics):
        lim = forest_limits([entries[k].get(m) for k in keys])
        for i, key in enumerate(keys):
            c = entries[key].get(m)
            if c is None:
                continue
            better = -c["mean_diff"] if m in LOWER_IS_BETTER else c["mean_diff"]
            color = ("0.45" if not excludes_zero(c["ci95"]) else "tab:green" if better > 0 else "tab:red")
            marker = "D" if "n_scenes" in c else "o"
            if c["ci95"] is None:
                ax.plot(c["mean_diff"], i, marker, mfc="none", mec=color)
            else:
                lo, hi = c["ci95"]
                shown = (max(lo, lim[0]), min(hi, lim[1]))
                ax.errorbar(c["mean_diff"], i, fmt=marker, color=color, capsize=3,
                            xerr=[[c["mean_diff"] - shown[0]], [shown[1] - c["mean_diff"]]])
                if shown != (lo, hi):          # a CI wider than the axis: arrows and its numbers
                    for end, side in ((lo, 0), (hi, 1)):
                        if end != shown[side]:
                            ax.plot(shown[side], i, "<>"[side], color=color, ms=5)
                    ax.annotate(f"[{lo:+.3g}, {hi:+.3g}]", (c["mean_diff"], i), xytext=(0, 5),
                                textcoords="offset points", ha="center", fontsize=7, color=color)
        ax.set_xlim(*lim)
        for i in range(1, len(keys)):
            if keys[i][0] != keys[i - 1][0]:
                ax.axhline(i - 0.5, color="0.8", lw=0.8)
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_title(f"Δ{m} vs {baseline}, {CONFIDENCE:.0%} CI\n"
                     f"({'lower' if m in LOWER_IS_BETTER else 'higher'} is better)", fontsize=9)
        ax.grid(axis="x", alpha=0.3)
        ax.xaxis.set_major_locator(plt.MaxNLocator(4))
    if keys:
        n = [next(iter(entries[k].values())) for k in keys]
        labels = [f"{k[0]} {k[1]}v {k[2]} ({'scenes' if 'n_scenes' in c else 'n'}="
                  f"{c.get('n_scenes', c.get('n_pairs'))})" for k, c in zip(keys, n)]
        axes[0][0].set_yticks(y, labels, fontsize=8)
        axes[0][0].set_ylim(len(keys) - 0.5, -0.5)                 # first row on top
    else:
        axes[0][0].text(0.5, 0.5, f"no run paired with {baseline}", ha="center", va="center",
                        transform=axes[0][0].transAxes)
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
                   help="compare every method with this method label (e.g. 3dgs) seed by seed: "
                        "difference, 95%% CI, paired t-test and Wilcoxon p, runs needed")
    t.add_argument("--out", default="table-out")


def tabulate(runs: list[dict], metrics=DEFAULT_METRICS, baseline: str | None = None) -> dict:
    """``aggregate``'s table plus, with a baseline, ``stats.compare``'s comparisons, details,
    pooled and unpaired lists (empty lists without one): the content of ``table.json``."""
    table = aggregate(runs, metrics, baseline)
    comp = (compare(runs, metrics, baseline) if baseline is not None
            else {"comparisons": [], "details": [], "pooled": [], "unpaired": []})
    return {**table, "alpha": ALPHA, "confidence": CONFIDENCE, "power": POWER, **comp}


def run(args) -> dict:
    doc = tabulate([load_run(r) for r in args.run_dirs], args.metrics, args.baseline)
    out = Path(args.out)
    md = markdown(doc)
    if doc["baseline"] is not None:
        md += "\n" + paired_markdown(doc, doc["metrics"], doc["baseline"])
    atomic_write_text(out / "table.md", md)
    atomic_write_text(out / "table.csv", _csv(doc, doc if doc["baseline"] is not None else None))
    atomic_write_json(out / "table.json", doc)
    plot(doc, out / "table.png")
    if doc["baseline"] is not None:
        forest(doc, doc["metrics"], doc["baseline"], out / "forest.png")
    print(md, end="")
    print(f"written to {out}")
    return doc


__all__ = ["aggregate", "tabulate", "load_run", "markdown", "paired_markdown", "method_label", "plot",
           "forest", "run"]
