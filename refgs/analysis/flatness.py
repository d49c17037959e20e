"""``refgs flatness``: how robust a trained model is to position perturbations (FM-12).

The paper's perturbation-robustness figure: apply Scale-Adaptive Perturbation to a trained model
-- by default with p = 1, alpha = 1 and no clamp (every Gaussian moved by gamma R S z), or with
the training settings (p = 0.3, the axis clamp) -- and measure PSNR on the training and the test
views, mean +- standard deviation over seeds, for each gamma.  A flatter minimum loses less.

    refgs flatness RUN_DIR [RUN_DIR ...] [--gammas 0 0.2 0.4 0.6 0.8 1.0] [--seeds 5]
                   [--settings flatness|training] [--backend NAME] [--out DIR]

Writes ``flatness.json``, ``flatness.csv`` and ``flatness.png`` (train and test panels, one curve
per run) into ``--out``; each curve of flatness.json carries ``run``: the run's name, scene,
views, method label (FM-13) and training seed.  Seeds: the perturbation of (gamma index k, seed s)
is drawn from ``np.random.default_rng([s, k])``, so every number is reproducible and each gamma
has its own stream.

Over training seeds (``group_over_seeds``, ``plot_over_seeds``; ``refgs figures --flatness ...
--over-seeds``): the curves are grouped by (scene, views) and method label, and per gamma the mean
over the group's runs of their PSNR (each a mean over perturbation seeds) is drawn with the 95 %
Student-t interval over the runs, ``mean +- t_{0.975, n-1} s / sqrt(n)``, where n >= 2.
"""
from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from scipy import stats

from ..errors import ConfigError
from ..io.atomic import atomic_save_figure, atomic_write_json, atomic_write_text
from ..metrics.psnr import psnr
from ..methods.flat_minima import DEFAULT_CLAMP, P_PERTURB, sap_offsets
from .stats import CONFIDENCE

#: Files written into ``--out``.
FLATNESS_JSON, FLATNESS_CSV, FLATNESS_PLOT = "flatness.json", "flatness.csv", "flatness.png"
#: The figure of ``plot_over_seeds`` (written by ``refgs figures --over-seeds``).
FLATNESS_OVER_SEEDS_PLOT = "flatness_over_seeds.png"
#: The paper's figure: gamma on the x axis, 5 seeds.  [FM-12]
DEFAULT_GAMMAS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
DEFAULT_SEEDS = 5
#: Perturbation settings.  "flatness": every Gaussian, full magnitude, no clamp (the analysis);
#: "training": the settings the method trains with at t = T (p = 0.3, alpha = 1, axis clamp).
SETTINGS = {"flatness": {"p": 1.0, "alpha": 1.0, "clamp": "none"},
            "training": {"p": P_PERTURB, "alpha": 1.0, "clamp": DEFAULT_CLAMP}}


def _mean_psnr(trainer, views, gaussians) -> float:
    return float(np.mean([psnr(trainer.render_view(v, gaussians), v.image) for v in views]))


def _check(gammas, seeds: int, settings: str) -> None:
    if settings not in SETTINGS:
        raise ConfigError(f"--settings: expected one of {sorted(SETTINGS)}, got {settings!r}")
    if seeds < 1:
        raise ConfigError(f"--seeds: expected at least 1, got {seeds}")
    if not gammas or any(not np.isfinite(g) or g < 0 for g in gammas):
        raise ConfigError(f"--gammas: expected finite values >= 0, got {list(gammas)}")


def flatness_curve(trainer, gammas=DEFAULT_GAMMAS, seeds: int = DEFAULT_SEEDS,
                   settings: str = "flatness", progress=None) -> dict:
    """PSNR of the trainer's model under SAP for each gamma (module docstring).

    Returns {"gammas", "settings", "train"/"test": {"mean", "std", "all" (gammas x seeds)}}; the
    standard deviation is the sample one (ddof 1), 0 for a single seed or gamma = 0.
    """
    _check(gammas, seeds, settings)
    opts = SETTINGS[settings]
    g = trainer.gaussians()
    res = {"gammas": [float(x) for x in gammas], "settings": settings, **opts}
    for split, views in (("train", trainer.train_views), ("test", trainer.test_views)):
        res[split] = {"all": []}
    clean = {split: _mean_psnr(trainer, views, g)
             for split, views in (("train", trainer.train_views), ("test", trainer.test_views))}
    for k, gamma in enumerate(gammas):
        rows = {"train": [], "test": []}
        for s in range(seeds):
            if gamma == 0:
                vals = clean
            else:
                off, _ = sap_offsets(g, gamma=float(gamma), p=opts["p"], alpha=opts["alpha"],
                                     clamp=opts["clamp"], rng=np.random.default_rng([s, k]))
                gh = g.replace(means=g.means + off)
                vals = {split: _mean_psnr(trainer, views, gh)
                        for split, views in (("train", trainer.train_views), ("test", trainer.test_views))}
            for split in rows:
                rows[split].append(vals[split])
            if progress is not None:
                progress()
        for split in rows:
            res[split]["all"].append(rows[split])
    for split in ("train", "test"):
        a = np.asarray(res[split]["all"])
        res[split]["mean"] = a.mean(axis=1).tolist()
        res[split]["std"] = (a.std(axis=1, ddof=1) if a.shape[1] > 1 else np.zeros(len(a))).tolist()
    return res


def plot_curves(curves: dict, path: Path) -> None:
    """{label: flatness_curve result} as train and test panels, PSNR against gamma (mean +- std)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharex=True)
    for ax, split in zip(axes, ("train", "test")):
        for label, c in curves.items():
            ax.errorbar(c["gammas"], c[split]["mean"], yerr=c[split]["std"], marker="o", capsize=3,
                        label=label)
        ax.set_title(f"{split} views")
        ax.set_xlabel(r"perturbation $\gamma$")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("robustness to position perturbations (SAP; mean +- std over seeds)")
    fig.tight_layout()
    atomic_save_figure(fig, path)


#: The training-seed suffix of a run name (``fern_v3_fm_s0``): groups the curves of flatness.json
#: files written before curves carried ``run``.
SEED_SUFFIX = re.compile(r"_s(\d+)$")


def curve_key(name: str, curve: dict) -> tuple[str, str, str]:
    """(condition, method label, seed) of a curve: from its ``run`` entry, else from its name
    (``fern3_fm_s0 (fm, t=10000)``: condition "", the run name without ``_s<seed>``)."""
    run = curve.get("run")
    if isinstance(run, dict) and {"scene", "views", "label", "seed"} <= set(run):
        return f"{run['scene']}, {run['views']} views", str(run["label"]), str(run["seed"])
    stem = name.split(" ")[0]
    m = SEED_SUFFIX.search(stem)
    return ("", stem[:m.start()], m.group(1)) if m else ("", stem, "")


def group_over_seeds(curves: dict) -> dict:
    """{condition: {label: {"n", "gammas", "runs", "train"/"test": {"mean", "lo", "hi"}}}}: per
    gamma the mean over the group's runs of their mean PSNR and the 95 % t-interval over the runs
    (``lo``/``hi`` None for one run); ConfigError when a group's gammas differ or two of its
    curves have one training seed."""
    groups: dict = {}
    seen: dict = {}
    for name, c in curves.items():
        cond, label, seed = curve_key(name, c)
        if seed and (cond, label, seed) in seen:
            raise ConfigError(f"flatness curves {seen[cond, label, seed]!r} and {name!r}: the same "
                              f"run ({cond or 'scene'} {label}, seed {seed}) twice")
        seen[cond, label, seed] = name
        groups.setdefault(cond, {}).setdefault(label, []).append((name, c))
    out: dict = {}
    for cond, by_label in sorted(groups.items()):
        for label, items in sorted(by_label.items()):
            gammas = items[0][1]["gammas"]
            for name, c in items[1:]:
                if c["gammas"] != gammas:
                    raise ConfigError(f"flatness curves {items[0][0]!r} and {name!r}: different "
                                      f"gammas {gammas} and {c['gammas']}")
            n = len(items)
            g = {"n": n, "gammas": gammas, "runs": [name for name, _ in items]}
            for split in ("train", "test"):
                a = np.asarray([c[split]["mean"] for _, c in items], np.float64)   # (n, gammas)
                mean = a.mean(axis=0)
                if n >= 2:
                    t_crit = stats.t.ppf(0.5 + CONFIDENCE / 2, n - 1)
                    half = t_crit * a.std(axis=0, ddof=1) / np.sqrt(n)
                    lo, hi = (mean - half).tolist(), (mean + half).tolist()
                else:
                    lo = hi = None
                g[split] = {"mean": mean.tolist(), "lo": lo, "hi": hi}
            out.setdefault(cond, {})[label] = g
    return out


def plot_over_seeds(curves: dict, path: Path) -> dict:
    """``group_over_seeds`` drawn: one row per condition, train and test panels, a line per
    method label with its 95 % band over seeds (no band for one seed); returns the groups."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_over_seeds(curves)
    fig, axes = plt.subplots(len(groups), 2, figsize=(10, 3.8 * len(groups)), squeeze=False)
    for row, (cond, by_label) in zip(axes, groups.items()):
        for ax, split in zip(row, ("train", "test")):
            for k, (label, g) in enumerate(by_label.items()):
                col = f"C{k % 10}"
                ax.plot(g["gammas"], g[split]["mean"], "o-", ms=3, color=col,
                        label=f"{label} (n={g['n']})")
                if g[split]["lo"] is not None:
                    ax.fill_between(g["gammas"], g[split]["lo"], g[split]["hi"], color=col,
                                    alpha=0.2, lw=0)
            ax.set_title(f"{cond + ': ' if cond else ''}{split} views", fontsize=9)
            ax.set_xlabel(r"perturbation $\gamma$")
            ax.set_ylabel("PSNR (dB)")
            ax.grid(alpha=0.3)
        row[0].legend(fontsize=8)
    fig.suptitle("robustness to position perturbations over training seeds (mean, 95 % t-band)")
    fig.tight_layout()
    atomic_save_figure(fig, path)
    return groups


def add_parser(sub) -> None:
    f = sub.add_parser("flatness", help="PSNR of trained runs under SAP position perturbations")
    f.add_argument("run_dirs", nargs="+")
    f.add_argument("--gammas", type=float, nargs="+", default=list(DEFAULT_GAMMAS))
    f.add_argument("--seeds", type=int, default=DEFAULT_SEEDS)
    f.add_argument("--settings", default="flatness", choices=sorted(SETTINGS))
    f.add_argument("--backend", help="render with this backend instead of the run's (a name of "
                   "refgs.backends or module:object)")
    f.add_argument("--out", default="flatness-out")
    f.add_argument("--quiet", action="store_true")


def run(args) -> dict:
    """The ``refgs flatness`` command; returns {run label: curve}."""
    from ..runs import load
    from .tables import method_label

    _check(args.gammas, args.seeds, args.settings)
    curves = {}
    trainers = []
    for rd in args.run_dirs:
        _, cfg, trainer = load(rd, backend=args.backend)
        label = f"{Path(rd).name} ({cfg.method}, t={trainer.t})"
        info = {"name": Path(rd).absolute().name, "scene": Path(cfg.scene).name, "views": cfg.views,
                "label": method_label(cfg.to_dict()), "seed": cfg.seed}
        trainers.append((label, trainer, info))
    total = len(trainers) * len(args.gammas) * args.seeds
    bar = None
    if not args.quiet:
        from tqdm import tqdm
        bar = tqdm(total=total, desc="flatness", unit="render set")
    for label, trainer, info in trainers:
        curves[label] = {**flatness_curve(trainer, args.gammas, args.seeds, args.settings,
                                          progress=(bar.update if bar is not None else None)),
                         "run": info}
    if bar is not None:
        bar.close()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / FLATNESS_JSON, {"runs": curves})
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["run", "gamma", "train_psnr_mean", "train_psnr_std", "test_psnr_mean", "test_psnr_std"])
    for label, c in curves.items():
        for i, gmm in enumerate(c["gammas"]):
            w.writerow([label, gmm, c["train"]["mean"][i], c["train"]["std"][i], c["test"]["mean"][i],
                        c["test"]["std"][i]])
    atomic_write_text(out / FLATNESS_CSV, buf.getvalue())
    plot_curves(curves, out / FLATNESS_PLOT)
    if not args.quiet:
        for label, c in curves.items():
            print(label)
            print("  gamma  " + "  ".join(f"{x:>12.2f}" for x in c["gammas"]))
            for split in ("train", "test"):
                print(f"  {split:5s}  " + "  ".join(f"{m:6.2f}+-{s:4.2f}" for m, s in
                                                  zip(c[split]["mean"], c[split]["std"])))
        print(f"written to {out}")
    return curves


__all__ = ["flatness_curve", "plot_curves", "curve_key", "group_over_seeds", "plot_over_seeds",
           "run", "DEFAULT_GAMMAS", "DEFAULT_SEEDS", "SETTINGS", "FLATNESS_JSON", "FLATNESS_CSV",
           "FLATNESS_PLOT", "FLATNESS_OVER_SEEDS_PLOT"]
