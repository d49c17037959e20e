"""How much of a trained model its scene needs: contributions and fragments (TRN-14, docs/compact.md).

``refgs compactness RUN ... --out DIR`` reads each run's final state and writes:

    compactness.json   per run: Gaussians, how many carry 90 / 99 / 99.9 % of the total blending
                       weight over the training views (refgs.train.contribution), the fragments
                       (pixel-Gaussian pairs) of a render of each training view, and from the
                       run's history the fragments per iteration in each phase of training
                       (between opacity resets / FM reinitialisations)
    compactness.md     the same as a Markdown table
    compactness.png    the cumulative share of the weight against the Gaussians (largest first),
                       and the fragments per iteration over training
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.atomic import atomic_save_figure, atomic_write_json, atomic_write_text
from ..train.contribution import CARRY_SHARES, contributions

COMPACTNESS_JSON = "compactness.json"
COMPACTNESS_MD = "compactness.md"
COMPACTNESS_PLOT = "compactness.png"
#: Phases of training for the fragment profile: every PHASE_LENGTH iterations, the period of the
#: FM reinitialisation (FM-06) and a third of 3DGS' opacity reset interval (TRN-06).
PHASE_LENGTH = 1000
#: Points of the cumulative curve in the plot.
CURVE_POINTS = 400


def fragment_phases(history: dict, length: int = PHASE_LENGTH) -> list[dict]:
    """Mean fragments per iteration and mean Gaussians in each block of ``length`` iterations
    (iterations without a count, -1, left out)."""
    t = np.asarray(history.get("train_t", []), np.int64)
    frag = np.asarray(history.get("fragments", []), np.float64)
    n = np.asarray(history.get("n_gaussians", []), np.float64)
    if len(frag) != len(t) or not len(t):
        return []
    phases = []
    for start in range(0, int(t.max()), length):
        sel = (t > start) & (t <= start + length) & (frag >= 0)
        if sel.any():
            phases.append({"from": start + 1, "to": min(start + length, int(t.max())),
                           "fragments": float(frag[sel].mean()), "gaussians": float(n[sel].mean())})
    return phases


def measure(run_dir, backend: str | None = None) -> dict:
    """The compactness of one run's final state (module docstring)."""
    import json

    from ..runs import HISTORY_FILE, load
    from .tables import method_label

    run_dir = Path(run_dir)
    config, cfg, trainer = load(run_dir, backend=backend)
    c = contributions(trainer.backend, trainer.gaussians(), [v.camera for v in trainer.train_views],
                      cfg.profile)
    history = json.loads((run_dir / HISTORY_FILE).read_text()) if (run_dir / HISTORY_FILE).is_file() else {}
    w = np.sort(c.weight)[::-1]
    share = np.cumsum(w) / max(float(w.sum()), np.finfo(float).tiny)
    pick = np.unique(np.linspace(0, len(w) - 1, min(CURVE_POINTS, len(w))).astype(int))
    return {"name": run_dir.absolute().name, "scene": Path(cfg.scene).name, "views": cfg.views,
            "method": method_label(cfg.to_dict()), "seed": cfg.seed, "iteration": trainer.t,
            "gaussians": trainer.n,
            "carried_by": {str(s): k for s, k in c.carried_by(CARRY_SHARES).items()},
            "fragments_per_view": [int(f) for f in c.fragments],
            "pixels_per_view": [int(p) for p in c.pixels],
            "fragments_per_pixel": float(c.fragments.sum() / c.pixels.sum()),
            "phases": fragment_phases(history),
            "curve": {"rank": [int(i + 1) for i in pick], "share": [float(share[i]) for i in pick]}}


def markdown(rows: list[dict]) -> str:
    """The table of docs/compact.md: one row a run."""
    head = ("| run | Gaussians | 90 % of the weight | 99 % | 99.9 % | fragments / view | "
            "fragments / pixel |\n|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        n, cb = r["gaussians"], r["carried_by"]
        cells = [f"{cb[str(s)]:,} ({cb[str(s)] / max(n, 1):.1%})" for s in CARRY_SHARES]
        lines.append(f"| {r['name']} | {n:,} | " + " | ".join(cells)
                     + f" | {np.mean(r['fragments_per_view']) / 1e6:.2f} M | {r['fragments_per_pixel']:.1f} |")
    return head + "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for k, r in enumerate(rows):
        a.plot(r["curve"]["rank"], r["curve"]["share"], color=f"C{k % 10}", label=r["name"])
        if r["phases"]:
            b.plot([p["to"] for p in r["phases"]], [p["fragments"] / 1e6 for p in r["phases"]],
                   "o-", ms=3, color=f"C{k % 10}", label=r["name"])
    a.set_xscale("log")
    a.set_xlabel("Gaussians, largest contribution first")
    a.set_ylabel("share of the total blending weight")
    a.grid(alpha=0.3)
    a.legend(fontsize=7)
    b.set_xlabel(f"iteration (mean over blocks of {PHASE_LENGTH})")
    b.set_ylabel("fragments per iteration (M)")
    b.grid(alpha=0.3)
    fig.tight_layout()
    atomic_save_figure(fig, path)
    return path


def add_parser(sub) -> None:
    p = sub.add_parser("compactness", help="contributions and fragments of trained runs "
                                            "(how many Gaussians carry the weight)")
    p.add_argument("run_dirs", nargs="+")
    p.add_argument("--backend", help="render with this backend instead of the run's")
    p.add_argument("--out", default="compactness-out")
    p.add_argument("--quiet", action="store_true")


def run(args) -> list[dict]:
    """The ``refgs compactness`` command."""
    rows = []
    for rd in args.run_dirs:
        rows.append(measure(rd, args.backend))
        if not args.quiet:
            print(markdown(rows[-1:]).splitlines()[-1])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / COMPACTNESS_JSON, {"runs": rows})
    atomic_write_text(out / COMPACTNESS_MD, markdown(rows))
    plot(rows, out / COMPACTNESS_PLOT)
    if not args.quiet:
        print(f"written to {out}")
    return rows


__all__ = ["measure", "markdown", "plot", "fragment_phases", "run", "COMPACTNESS_JSON",
           "COMPACTNESS_MD", "COMPACTNESS_PLOT", "PHASE_LENGTH"]
