"""The quality-cost frontier of a grid's report: test PSNR / SSIM / LPIPS against the training
loop's time and the Gaussians at T, one point per record (TRN-14, docs/compact.md; FM-15: every
point a record).

    refgs frontier GRID.toml [--records results/records] [--out frontier.png]

The records are those the report counts (its own grid's and its included grids', refgs.analysis
.report), restricted to the (scene, views) of the grid's own groups and to the methods of its
comparisons (both sides).  Per scene two rows of panels, one per metric: against the training
loop in minutes (refgs.analysis.cost.loop_seconds: the sum of the record's ``iter_seconds``,
setup and the final evaluation left out) and against the Gaussians at T.  Each record is a small
point, each method's mean over its seeds a large one, joined to its seeds.  Times are only comparable on one
machine: each point's marker says which CPU made it (``provenance.float_environment.numba_cpu``;
"unrecorded" for records older than that field), and the legend lists them.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_save_figure
from ..runs import CONFIG_FILE, HISTORY_FILE
from .cost import loop_seconds
from .report import all_runs
from .report_spec import load_report
from .report_tables import metric
from .tables import read_run_json

DEFAULT_OUT = "frontier.png"
#: (metrics.json key, axis label) of the panels, in order.
FRONTIER_METRICS = (("psnr", "test PSNR (dB)"), ("ssim", "test SSIM"),
                    ("lpips_vgg", "test LPIPS-VGG (lower is better)"))
#: The machine of a record without ``provenance.float_environment``.
UNRECORDED_CPU = "unrecorded"
#: Marker per machine, in order of first appearance.
CPU_MARKERS = ("o", "s", "^", "D", "v", "P")


@dataclass(frozen=True)
class FrontierPoint:
    """One record on the frontier."""

    record: str
    scene: str
    views: int
    method: str
    seed: int
    loop_minutes: float
    gaussians: float
    cpu: str
    metrics: dict


def record_cpu(config: dict) -> str:
    """The CPU target that made a record (module docstring)."""
    env = (config.get("provenance") or {}).get("float_environment") or {}
    return str(env.get("numba_cpu") or UNRECORDED_CPU)


def frontier_points(grid, records_dir) -> list[FrontierPoint]:
    """The points of the frontier of ``grid`` (module docstring); ConfigError when a record
    lacks its history or a metric."""
    report = load_report(grid)
    groups = set(report.groups)
    methods = {m for pair in report.comparisons for m in pair}
    points = []
    for r in all_runs(records_dir, report):
        if (r.scene, r.views) not in groups or (methods and r.method not in methods):
            continue
        folder = Path(records_dir) / r.record
        config = read_run_json(folder / CONFIG_FILE)
        loop = loop_seconds(config, read_run_json(folder / HISTORY_FILE), str(folder))
        values = {k: metric(r, k) for k, _ in FRONTIER_METRICS}
        gaussians = metric(r, "n_gaussians")
        if gaussians is None or any(v is None for v in values.values()):
            raise ConfigError(f"{folder}/metrics.json: expected n_gaussians and "
                              f"{', '.join(k for k, _ in FRONTIER_METRICS)}")
        points.append(FrontierPoint(r.record, r.scene, r.views, r.method, r.seed,
                                    loop / 60.0, gaussians, record_cpu(config), values))
    return points


def plot(points: list[FrontierPoint], path, names: dict | None = None,
         title: str = "") -> Path:
    """The figure of the module docstring, written atomically to ``path``."""
    if not points:
        raise ConfigError("frontier: no records of the grid yet (run and record it first)")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    names = names or {}
    thousands = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v / 1000:.0f}k")
    groups = sorted({(p.scene, p.views) for p in points})
    methods = sorted({p.method for p in points})
    cpus = list(dict.fromkeys(p.cpu for p in points))
    colour = {m: f"C{k % 10}" for k, m in enumerate(methods)}
    marker = {c: CPU_MARKERS[k % len(CPU_MARKERS)] for k, c in enumerate(cpus)}
    nm = len(FRONTIER_METRICS)
    fig, axes = plt.subplots(2 * len(groups), nm, figsize=(4.2 * nm, 3.3 * 2 * len(groups)),
                             squeeze=False)
    for g, (scene, views) in enumerate(groups):
        for row, (xkey, xlabel) in enumerate((("loop_minutes", "training loop (min)"),
                                              ("gaussians", "Gaussians at T"))):
            for col, (key, label) in enumerate(FRONTIER_METRICS):
                ax = axes[2 * g + row, col]
                for m in methods:
                    pts = [p for p in points if (p.scene, p.views, p.method) == (scene, views, m)]
                    if not pts:
                        continue
                    xs = np.array([getattr(p, xkey) for p in pts])
                    ys = np.array([p.metrics[key] for p in pts])
                    for p, x, y in zip(pts, xs, ys):
                        ax.plot([xs.mean(), x], [ys.mean(), y], "-", color=colour[m], lw=0.6,
                                alpha=0.5)
                        ax.plot(x, y, marker[p.cpu], ms=4, color=colour[m], alpha=0.7)
                    ax.plot(xs.mean(), ys.mean(), marker[pts[0].cpu], ms=10, color=colour[m],
                            mec="black", label=f"{names.get(m, m)} (n={len(pts)})")
                ax.set_xlabel(xlabel)
                ax.set_ylabel(label)
                ax.grid(alpha=0.3)
                if xkey == "gaussians":
                    ax.set_xscale("log")
                    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
                    ax.xaxis.set_major_formatter(thousands)
                    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
                ax.set_title(f"{scene}, {views} views", fontsize=9)
        axes[2 * g, 0].legend(fontsize=7)
    cpu_text = ", ".join(f"{marker[c]} = {c}" for c in cpus)
    fig.suptitle(f"{title}\nmarkers: the CPU that made the record ({cpu_text}); large = mean "
                 "over seeds", fontsize=9)
    fig.tight_layout()
    atomic_save_figure(fig, Path(path))
    return Path(path)


def add_parser(sub) -> None:
    p = sub.add_parser("frontier", help="test metrics against training time and Gaussians, "
                                        "from a grid's records (docs/compact.md)")
    p.add_argument("grid", help="a grid file with a [report] table")
    p.add_argument("--records", default="results/records")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"the figure (default {DEFAULT_OUT})")


def run(args) -> Path:
    """The ``refgs frontier`` command."""
    report = load_report(args.grid)
    path = plot(frontier_points(args.grid, args.records), args.out, report.names, report.title)
    print(f"written to {path}")
    return path


__all__ = ["FrontierPoint", "frontier_points", "plot", "record_cpu", "add_parser", "run",
           "FRONTIER_METRICS", "DEFAULT_OUT"]
