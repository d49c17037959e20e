"""``refgs figures``: the pictures behind docs/results.md, made from finished runs (FM-14).

    refgs figures RUN_DIR [RUN_DIR ...] [--flatness DIR_OR_JSON ...] [--over-seeds]
                  [--out figures]
    refgs figures --compare RUN_DIR [RUN_DIR ...] [--seed 0] [--view 0] [--out figures]

One command, one folder (``figures/`` by default, which git ignores: renders of the real
scenes are not committed).  It writes

- ``renders_<run>.png`` -- for each run, every test view: the render beside its ground truth and
  the per-pixel absolute error (mean over channels), titled with the view's PSNR;
- ``psnr_trajectories.png`` -- test PSNR against iteration of all runs in one panel and the
  running mean of the training PSNR in another, each run labelled by its method label
  (``fm`` vs ``fm[reinit=False]``, FM-13) so that runs with and without reinitialisation sit side
  by side; the reinitialisation iterations of the runs that reinitialise are marked;
- ``gaussians.png`` -- the number of Gaussians against iteration;
- ``flatness.png`` -- the curves of every ``flatness.json`` given with ``--flatness`` (the output
  of ``refgs flatness``) in one figure;
- ``flatness_over_seeds.png`` (with ``--over-seeds``) -- those curves grouped by scene and method
  label, the mean over training seeds with its 95 % t-band (refgs.analysis.flatness);
- ``compare_<scene>_v<views>_s<seed>.png`` (with ``--compare``, instead of the per-run figures) --
  ground truth | 3DGS | DropGaussian | FM on one test view with a magnified crop, per scene
  (refgs.analysis.qualitative);
- ``index.md`` -- what each file shows and which runs it was made from.

Renders are read from ``RUN/renders/test/`` (written when the run finished); a run without them is
rendered from its checkpoint; a record (``refgs record``: config, metrics and history only) gets
the curves but no renders, which index.md says.  Ground truth is loaded from the scene in the run's config.json.
Nothing is trained or perturbed here, so the command takes seconds, not hours.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_path, atomic_write_text

#: Upper end of the error colour map (absolute error, images in [0, 1]); larger errors saturate.
ERROR_VMAX = 0.25
#: Window of the running mean of the training PSNR (iterations); the per-iteration value
#: jumps between the training views.
TRAIN_PSNR_WINDOW = 100
DEFAULT_OUT = "figures"


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", name)


def load_figure_run(run_dir: str | Path) -> dict:
    """config, metrics, history and label of a finished run; ConfigError naming the file."""
    from ..runs import CONFIG_FILE, HISTORY_FILE, METRICS_FILE
    from .tables import method_label, read_run_json

    run_dir = Path(run_dir).absolute()
    config = read_run_json(run_dir / CONFIG_FILE)
    metrics = read_run_json(run_dir / METRICS_FILE)
    history = read_run_json(run_dir / HISTORY_FILE)
    s = config.get("settings", {})
    label = f"{method_label(s)} s{s.get('seed')}"
    return {"dir": run_dir, "name": run_dir.name, "config": config, "settings": s,
            "metrics": metrics, "history": history, "label": label}


def reinit_iterations(settings: dict) -> list[int]:
    """Iterations at which the run's method reinitialises (FM-06); [] if it does not."""
    from ..methods.flat_minima import REINIT_INTERVAL, is_reinit_iteration

    params = settings.get("method_params") or {}
    uses_fm = settings.get("method") == "fm" or params.get("fm", False)
    if not uses_fm or not params.get("reinit", True):
        return []
    interval = int(params.get("reinit_interval", REINIT_INTERVAL))
    total = int(settings["iters"])
    return [t for t in range(1, total + 1) if is_reinit_iteration(t, total, interval)]


def _pairs(run: dict, views_cache: dict):
    """[(view name, render (H, W, 3), ground truth (H, W, 3))] of a run's test views."""
    from PIL import Image

    from ..runs import RENDER_DIR, load, load_views
    from ..train.trainer import TrainConfig

    cfg = TrainConfig.from_dict(run["settings"])
    key = (cfg.scene, cfg.images, cfg.resolution, cfg.views, cfg.holdout, cfg.dtype)
    if key not in views_cache:                    # runs of one scene share its ground truth
        views_cache[key] = load_views(cfg)[4]
    test_views = views_cache[key]
    out, trainer = [], None
    for v in test_views:
        png = run["dir"] / RENDER_DIR / "test" / (Path(v.name).stem + ".png")
        if png.is_file():
            img = np.asarray(Image.open(png).convert("RGB"), np.float64) / 255.0
        else:
            if trainer is None:
                trainer = load(run["dir"]).trainer
            img = trainer.render_view(v)
        gt = np.asarray(v.image, np.float64)
        if img.shape != gt.shape:
            raise ConfigError(f"{png}: {img.shape[1]}x{img.shape[0]} render, but the view "
                              f"{v.name} is {gt.shape[1]}x{gt.shape[0]}")
        out.append((v.name, img, gt))
    return out


def has_images(run: dict) -> bool:
    """Whether a run's test renders can be shown: saved PNGs or a checkpoint to render from
    (a record of ``refgs record`` has neither)."""
    from ..runs import CHECKPOINT_FILE, RENDER_DIR

    return (run["dir"] / RENDER_DIR / "test").is_dir() or (run["dir"] / CHECKPOINT_FILE).is_file()


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


def plot_renders(run: dict, path: Path, views_cache: dict | None = None) -> None:
    """Render | ground truth | |error| for each test view of one run (``views_cache``: test views
    already loaded, keyed by scene settings, shared between the runs of one call)."""
    import matplotlib.pyplot as plt
    from ..metrics.psnr import psnr

    pairs = _pairs(run, {} if views_cache is None else views_cache)
    if not pairs:
        raise ConfigError(f"{run['dir']}: the run has no test views")
    h, w = pairs[0][1].shape[:2]
    fig, axes = plt.subplots(len(pairs), 3, figsize=(3 * 3.2, len(pairs) * 3.2 * h / w + 0.6),
                             squeeze=False)
    for row, (name, img, gt) in zip(axes, pairs):
        err = np.abs(img - gt).mean(axis=2)
        row[0].imshow(np.clip(img, 0, 1))
        row[0].set_title(f"render {name}\nPSNR {psnr(img, gt):.2f} dB", fontsize=8)
        row[1].imshow(gt)
        row[1].set_title("ground truth", fontsize=8)
        im = row[2].imshow(err, cmap="magma", vmin=0, vmax=ERROR_VMAX)
        row[2].set_title(f"|error| (mean {err.mean():.3f})", fontsize=8)
        for ax in row:
            ax.axis("off")
    fig.colorbar(im, ax=axes[:, 2].tolist(), shrink=0.8)
    fig.suptitle(f"{run['name']}: {run['label']}, {run['metrics'].get('n_gaussians')} Gaussians",
                 fontsize=9)
    _save(fig, path)


def plot_trajectories(runs: list, path: Path) -> None:
    """Test PSNR and running-mean train PSNR against iteration; reinit iterations marked."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    marked = set()
    for k, run in enumerate(runs):
        c = f"C{k % 10}"
        h = run["history"]
        if h.get("test_t"):
            axes[0].plot(h["test_t"], h["test_psnr"], "o-", ms=3, color=c, label=run["label"])
        t, p = np.asarray(h.get("train_t", []), float), np.asarray(h.get("train_psnr", []), float)
        if len(t) >= TRAIN_PSNR_WINDOW:
            m = np.convolve(p, np.ones(TRAIN_PSNR_WINDOW) / TRAIN_PSNR_WINDOW, mode="valid")
            axes[1].plot(t[TRAIN_PSNR_WINDOW - 1:], m, color=c, lw=1, label=run["label"])
        for r in reinit_iterations(run["settings"]):
            if r not in marked:
                marked.add(r)
                for ax in axes:
                    ax.axvline(r, color="0.6", lw=0.7, ls=":")
    axes[0].set_title("test PSNR" + (" (dotted: reinitialisation)" if marked else ""))
    axes[1].set_title(f"train PSNR, running mean of {TRAIN_PSNR_WINDOW} iterations")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)


def plot_gaussians(runs: list, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for k, run in enumerate(runs):
        h = run["history"]
        if h.get("n_gaussians"):
            ax.plot(h["train_t"][:len(h["n_gaussians"])], h["n_gaussians"], color=f"C{k % 10}",
                    label=run["label"])
    ax.set_xlabel("iteration")
    ax.set_ylabel("Gaussians")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)


def load_flatness(paths) -> dict:
    """{label: curve} from flatness.json files or the folders that hold them."""
    from .flatness import FLATNESS_JSON
    from .tables import read_run_json

    curves = {}
    for p in paths:
        p = Path(p)
        f = p / FLATNESS_JSON if p.is_dir() else p
        data = read_run_json(f)
        if "runs" not in data:
            raise ConfigError(f"{f}: expected the output of refgs flatness (a 'runs' entry)")
        for label, c in data["runs"].items():
            curves[label if label not in curves else f"{label} ({f})"] = c
    return curves


def make_figures(run_dirs, flatness=(), out: str | Path = DEFAULT_OUT, compare: bool = False,
                 seed: int = 0, view: int = 0, over_seeds: bool = False) -> list[Path]:
    """Every figure of the module docstring into ``out``; returns the files written.
    ``compare``: the runs make the comparisons of refgs.analysis.qualitative (runs of ``seed``,
    test view ``view``) instead of the per-run figures; ``over_seeds``: also the flatness curves
    over training seeds."""
    from . import qualitative
    from .flatness import FLATNESS_OVER_SEEDS_PLOT, group_over_seeds, plot_over_seeds
    from .flatness import plot_curves as plot_flatness

    if not run_dirs and not flatness:
        raise ConfigError("refgs figures: give at least one RUN_DIR or --flatness")
    if over_seeds and not flatness:
        raise ConfigError("--over-seeds: give the flatness.json files with --flatness")
    # read everything before writing anything
    groups = qualitative.plan(run_dirs, seed, view) if compare and run_dirs else {}
    runs = [] if compare else [load_figure_run(d) for d in run_dirs]
    curves = load_flatness(flatness)
    over = group_over_seeds(curves) if over_seeds else {}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib
    matplotlib.use("Agg")
    views_cache: dict = {}
    written, index = [], ["# refgs figures", "", "Made by `refgs figures` (refgs/analysis/figures.py).", ""]
    for run in runs:
        if not has_images(run):
            index.append(f"- no renders of {run['dir']} ({run['label']}): a record (refgs "
                         "record), without images or checkpoint")
            continue
        path = out / f"renders_{_safe(run['name'])}.png"
        plot_renders(run, path, views_cache)
        written.append(path)
        index.append(f"- `{path.name}`: test renders | ground truth | error of {run['dir']} "
                     f"({run['label']}, PSNR {run['metrics'].get('psnr', float('nan')):.2f})")
    if runs:
        for name, fn, what in (("psnr_trajectories.png", plot_trajectories, "test/train PSNR "
                                "against iteration"),
                               ("gaussians.png", plot_gaussians, "Gaussian count against iteration")):
            fn(runs, out / name)
            written.append(out / name)
            index.append(f"- `{name}`: {what} of " + ", ".join(r["name"] for r in runs))
    for path, line in qualitative.make_comparisons(groups, out, seed, view):
        written.append(path)
        index.append(f"- {line}")
    if curves:
        plot_flatness(curves, out / "flatness.png")
        written.append(out / "flatness.png")
        index.append("- `flatness.png`: PSNR under SAP against gamma of " + ", ".join(curves))
    if over_seeds:
        path = out / FLATNESS_OVER_SEEDS_PLOT
        plot_over_seeds(curves, path)
        written.append(path)
        which = "; ".join(f"{cond or 'runs'}: "
                          + ", ".join(f"{lab} (n={g['n']})" for lab, g in by.items())
                          for cond, by in over.items())
        index.append(f"- `{path.name}`: mean PSNR under SAP over training seeds, 95 % t-band where "
                     f"n >= 2, of {which}")
    atomic_write_text(out / "index.md", "\n".join(index) + "\n")
    return written + [out / "index.md"]


def add_parser(sub) -> None:
    f = sub.add_parser("figures", help="renders beside ground truth, PSNR trajectories and "
                                       "flatness curves of finished runs, into one folder")
    f.add_argument("run_dirs", nargs="*")
    f.add_argument("--flatness", nargs="+", default=[],
                   help="flatness.json files (or their folders) written by refgs flatness")
    f.add_argument("--over-seeds", action="store_true",
                   help="with --flatness: also the curves grouped by scene and method, mean over "
                        "training seeds with a 95%% t-band")
    f.add_argument("--compare", action="store_true",
                   help="instead of per-run figures: ground truth | 3DGS | DropGaussian | FM per "
                        "scene on one test view, with a zoomed crop")
    f.add_argument("--seed", type=int, default=0, help="with --compare: the runs' seed (default 0)")
    f.add_argument("--view", type=int, default=0,
                   help="with --compare: index into the test views (default 0)")
    f.add_argument("--out", default=DEFAULT_OUT, help="folder (default figures/, git-ignored)")
    f.add_argument("--quiet", action="store_true")


def run(args) -> list[Path]:
    written = make_figures(args.run_dirs, args.flatness, args.out, args.compare, args.seed,
                           args.view, args.over_seeds)
    if not args.quiet:
        for p in written:
            print(p)
    return written


__all__ = ["make_figures", "load_figure_run", "has_images", "load_flatness", "reinit_iterations",
           "ERROR_VMAX", "TRAIN_PSNR_WINDOW"]
