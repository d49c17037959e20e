"""``refgs`` command line: train (new or --resume), eval, render, demo (docs/spec/training.md).

    refgs train --scene DIR --views N --iters N --out DIR [--images images_8] [--resolution R]
                [--method 3dgs] [--seed S] [--backend reference] [--init-points train-views|sfm-all|PATH.ply]
                [--checkpoint-every K] [--eval-every K] [--strict] [--dtype float64|float32] ...
    refgs train --resume RUN_DIR
    refgs eval RUN_DIR [--model PATH.ply] [--no-lpips]
    refgs render RUN_DIR [--split test|train|all]
    refgs demo [--out DIR] [--iters N]
    refgs bench [--n N ...] [--size WxH ...] [--backends ...] [--fern-run RUN] [--out DIR]
    refgs flatness RUN_DIR ... [--gammas G ...] [--seeds S] [--settings flatness|training]
    refgs table RUN_DIR ... [--metrics psnr ssim lpips_vgg] [--baseline LABEL] [--out DIR]
    refgs figures RUN_DIR ... [--flatness DIR ...] [--out figures]

Bad input (missing folder, corrupt model, empty image folder, unsupported camera, --views too
large, ...) ends with ONE line ``refgs: error: ...`` on stderr naming the file or flag, exit
status 2, and no run directory left behind (TRN-09).  Ctrl-C / SIGTERM during training writes a
checkpoint and exits with status 130; ``refgs train --resume RUN_DIR`` continues it exactly.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from .errors import ConfigError, RefgsError
from .io.atomic import atomic_path, atomic_save_png, atomic_write_json
from .io.ply import read_gaussians_ply, write_gaussians_ply
from .train.backend import available_backends, get_backend
from .train.checkpoint import (CHECKPOINT_FILE, CONFIG_FILE, CheckpointError, RunDir,
                               load_checkpoint, peak_rss_gb, provenance, read_config,
                               save_checkpoint, source_hash, write_config)
from .train.densify import DENSIFY_PRESETS, SCREEN_SIZE_RULES
from .train.loss import LOSS_FORMS
from .train.schedule import scene_extent
from .train.trainer import BACKGROUNDS, DTYPES, METHODS, TrainConfig, Trainer, View
from .methods import training as _methods  # noqa: F401  (registers fm, dropgaussian)
from .methods.flat_minima import CLAMP_MODES, PERTURB_TARGETS

#: Exit statuses: bad input, interrupted (128 + SIGINT), other failure.
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_FAILURE = 1
#: Files of a run directory besides config.json / checkpoint.npz.
MODEL_FILE = "model.ply"
INIT_FILE = "init_points.ply"
METRICS_FILE = "metrics.json"
HISTORY_FILE = "history.json"
PLOT_FILE = "psnr.png"
RENDER_DIR = "renders"
#: Smallest image side LPIPS accepts (refgs.metrics.lpips docstring: vgg >= 16, alex >= 31).
LPIPS_MIN_SIDE = {"vgg": 16, "alex": 31}
#: The three LPIPS variants reported: (key, net, input convention) (MET-05, MET-06).
LPIPS_VARIANTS = (("lpips_vgg", "vgg", "01"), ("lpips_vgg_official", "vgg", "official"),
                  ("lpips_alex", "alex", "official"))
#: `refgs demo` defaults: views and iterations (chosen to take a few minutes on 2 cores), and
#: densification brought forward from the preset's 500/100 so that a short demo densifies
#: (at 150, 200, 250 for 300 iterations).  Our choice.
DEMO_VIEWS = 3
DEMO_ITERS = 300
DEMO_DENSIFY = {"start": 100, "interval": 50}


class Interrupted(Exception):
    """Training stopped by Ctrl-C / SIGTERM after writing a checkpoint."""

    def __init__(self, run_dir: Path, iteration: int):
        super().__init__(f"interrupted at iteration {iteration}; checkpoint written to "
                         f"{run_dir / CHECKPOINT_FILE}; continue with: refgs train --resume {run_dir}")
        self.run_dir, self.iteration = run_dir, iteration


class StopFlag:
    """Set by the first SIGINT/SIGTERM (or a test): the loop finishes the iteration, writes a
    checkpoint and stops.  A second signal aborts at once (KeyboardInterrupt; the last periodic
    checkpoint stays valid)."""

    def __init__(self, notice: bool = False):
        self.requested = False
        self.notice = notice

    def set(self, *_):
        if self.requested and _:
            raise KeyboardInterrupt
        self.requested = True
        if self.notice and _:
            sys.stderr.write("\nrefgs: stopping after this iteration (press Ctrl-C again to abort)\n")

    def __enter__(self):
        self._old = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self.set)
        return self

    def __exit__(self, *exc):
        for sig, handler in self._old.items():
            signal.signal(sig, handler)


# --- scenes and views ---------------------------------------------------------------------------
def load_views(cfg: TrainConfig):
    """(scene, train_idx, test_idx, train_views, test_views) for a config (DAT clauses).

    Warnings raised while loading are shown only when loading succeeds, so that bad input ends
    with exactly one line (the error)."""
    from .data import load_scene
    from .data.split import split_views

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(cfg.scene, images=cfg.images, resolution=cfg.resolution,
                           strict=cfg.strict, dtype=DTYPES[cfg.dtype])
        train_idx, test_idx = split_views(scene.names, cfg.views, cfg.holdout)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    mk = lambda idx: [View(scene.names[i], scene.cameras[i], scene.images[i]) for i in idx]  # noqa: E731
    return scene, train_idx, test_idx, mk(train_idx), mk(test_idx)


def initial_points(cfg: TrainConfig, scene, train_idx, work_dir: Path):
    """(points (P, 3), colours (P, 3) in [0, 1]) for --init-points."""
    from .data.pointcloud import read_ply

    if cfg.init_points == "train-views":
        from .data.triangulate import triangulate_train_views
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            points, colors = triangulate_train_views(scene, train_idx, work_dir, cfg.triangulation,
                                                     seed=cfg.seed)
    elif cfg.init_points == "sfm-all":
        points, colors = scene.points, scene.point_colors
    elif cfg.init_points.lower().endswith(".ply"):
        points, colors = read_ply(cfg.init_points)
    else:
        raise ConfigError(f"--init-points: expected train-views, sfm-all or a .ply file, got "
                          f"{cfg.init_points!r}")
    if len(points) == 0:
        raise ConfigError(f"--init-points {cfg.init_points}: no points (try --init-points sfm-all "
                          "or a PLY file)")
    return np.asarray(points, np.float64), np.asarray(colors, np.float64)


def absolute_paths(cfg: TrainConfig) -> TrainConfig:
    """The config with the scene folder and a PLY --init-points made absolute (so that
    ``--resume`` works from any folder)."""
    init = cfg.init_points
    if init.lower().endswith(".ply"):
        init = str(Path(init).absolute())
    return dataclasses.replace(cfg, scene=str(Path(cfg.scene).absolute()), init_points=init)


def settings_hash(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


# --- the loop with checkpoints --------------------------------------------------------------------
def _checkpoint(trainer: Trainer, run: RunDir) -> None:
    meta = trainer.state_meta()
    meta["settings_hash"] = settings_hash(trainer.cfg.to_dict())
    save_checkpoint(run / CHECKPOINT_FILE, trainer.state_arrays(), meta)
    run.publish()


def _loop(trainer: Trainer, run: RunDir, progress: bool, callback=None) -> None:
    from tqdm import tqdm

    cfg = trainer.cfg
    bar = tqdm(total=cfg.iters, initial=trainer.t, disable=not progress, desc="train",
               unit="it", file=sys.stderr, dynamic_ncols=True)
    with StopFlag(notice=progress) as stop:
        try:
            while trainer.t < cfg.iters:
                info = trainer.step()
                t = trainer.t
                bar.update(1)
                bar.set_postfix(loss=f"{trainer.loss_ema:.4f}", psnr=f"{info['psnr']:.2f}",
                                n=trainer.n, refresh=False)
                if cfg.eval_interval and t % cfg.eval_interval == 0 and t < cfg.iters:
                    value = trainer.test_psnr()
                    if progress:
                        bar.write(f"[{t}] test PSNR {value:.3f} dB", file=sys.stderr)
                if callback is not None:
                    callback(trainer, stop)
                if t < cfg.iters and (stop.requested or
                                      (cfg.checkpoint_every and t % cfg.checkpoint_every == 0)):
                    _checkpoint(trainer, run)
                    if stop.requested:
                        raise Interrupted(run.path, t)
        finally:
            bar.close()


def _make_trainer(cfg: TrainConfig, train_views, test_views, params: dict) -> Trainer:
    extent = scene_extent([v.camera.center for v in train_views])
    if extent == 0.0:
        warnings.warn("one training view: scene extent 0, positions will not move (as in 3DGS)",
                      stacklevel=2)
    return Trainer(cfg, train_views, test_views, params, extent, get_backend(cfg.backend))


def train(cfg: TrainConfig, out: str | Path, progress: bool = True, callback=None,
          command: list | None = None) -> Path:
    """Start a new run in ``out`` (TRN-07..TRN-09); returns the run directory."""
    from .data.init import init_gaussians_from_points
    from .data.pointcloud import write_ply

    cfg = absolute_paths(cfg).validate()
    get_backend(cfg.backend)
    if cfg.method not in METHODS:
        raise ConfigError(f"--method: expected one of {sorted(METHODS)}, got {cfg.method!r}")
    final = Path(out).absolute()
    if final.exists():
        raise ConfigError(f"--out: {final} already exists (choose a new folder, or continue it "
                          f"with: refgs train --resume {final})")
    scene, train_idx, test_idx, train_views, test_views = load_views(cfg)
    run = RunDir.create(final)
    try:
        points, colors = initial_points(cfg, scene, train_idx, run.path)
        write_ply(run / INIT_FILE, points, colors)
        g = init_gaussians_from_points(points, colors, cfg.sh_degree, DTYPES[cfg.dtype])
        trainer = _make_trainer(cfg, train_views, test_views, g.to_dict())
        trainer.init_cloud = {"points": np.asarray(points), "colors": np.asarray(colors)}
        write_config(run, {
            "refgs_version": _version(), "command": command, "settings": cfg.to_dict(),
            "settings_hash": settings_hash(cfg.to_dict()),
            "train_images": [v.name for v in train_views], "test_images": [v.name for v in test_views],
            "image_size": [train_views[0].camera.width, train_views[0].camera.height],
            "n_init_points": int(len(points)), "extent": trainer.extent,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "provenance": provenance(), "resumes": []})
        _loop(trainer, run, progress, callback)
        _checkpoint(trainer, run)
    except BaseException:
        run.discard()
        raise
    finish(run.path, trainer, progress)
    return run.path


def _restore(run_dir: Path):
    """(config dict, TrainConfig, trainer with the checkpoint loaded) of a run directory."""
    config = read_config(run_dir)
    try:
        cfg = TrainConfig.from_dict(config["settings"]).validate()
    except (KeyError, TypeError) as exc:
        raise CheckpointError(f"{run_dir / CONFIG_FILE}: bad settings ({exc})") from None
    arrays, meta = load_checkpoint(run_dir / CHECKPOINT_FILE)
    if meta.get("settings_hash") != settings_hash(cfg.to_dict()):
        raise CheckpointError(f"{run_dir / CONFIG_FILE}: settings differ from those of "
                              f"{run_dir / CHECKPOINT_FILE} (edited after the run started?)")
    _, _, _, train_views, test_views = load_views(cfg)
    names = ([v.name for v in train_views], [v.name for v in test_views])
    if names != (config.get("train_images"), config.get("test_images")):
        raise CheckpointError(f"{cfg.scene}: its train/test views differ from {run_dir / CONFIG_FILE}")
    params = {k[6:]: v for k, v in arrays.items() if k.startswith("param/")}
    trainer = _make_trainer(cfg, train_views, test_views, params)
    trainer.load_state(arrays, meta)
    return config, cfg, trainer


def resume(run_dir: str | Path, progress: bool = True, callback=None) -> Path:
    """Continue an interrupted run to its --iters (TRN-09); a finished run is only completed
    (outputs written if missing)."""
    from .data.pointcloud import write_ply

    run = RunDir.existing(run_dir)
    config, cfg, trainer = _restore(run.path)
    if trainer.init_cloud is not None and not (run.path / INIT_FILE).is_file():
        write_ply(run.path / INIT_FILE, trainer.init_cloud["points"], trainer.init_cloud["colors"])
    if trainer.t < cfg.iters:
        before = config.get("provenance", {}).get("source_hash")
        if before and before != source_hash():
            warnings.warn(f"{run.path}: the refgs source changed since the run started (source "
                          f"hash {before} -> {source_hash()}); the result can differ from an "
                          "uninterrupted run", stacklevel=2)
        config["resumes"] = config.get("resumes", []) + [
            {"from_iteration": trainer.t, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
             "provenance": provenance()}]
        write_config(run, config)
        _loop(trainer, run, progress, callback)
        _checkpoint(trainer, run)
    if trainer.t == cfg.iters and not (run.path / METRICS_FILE).is_file():
        finish(run.path, trainer, progress)
    return run.path


# --- evaluation and outputs -----------------------------------------------------------------------
def _lpips_all(img, gt, enabled: bool) -> dict:
    from .metrics import lpips_or_none

    out = {}
    for key, net, conv in LPIPS_VARIANTS:
        ok = enabled and min(img.shape[:2]) >= LPIPS_MIN_SIDE[net]
        out[key] = lpips_or_none(img, gt, net, conv) if ok else None
    return out


def evaluate(trainer: Trainer, lpips: bool = True, render_dir: Path | None = None) -> dict:
    """Metrics of the clamped renders of the test views (TRN-07); PNGs to ``render_dir``."""
    from .metrics import ssim, ssim_skimage
    from .metrics.psnr import psnr

    per_view = []
    for v in trainer.test_views:
        img = trainer.render_view(v)
        if render_dir is not None:
            atomic_save_png(render_dir / (Path(v.name).stem + ".png"), img)
        gt = np.asarray(v.image, np.float64)
        row = {"name": v.name, "psnr": psnr(img, gt), "ssim": ssim(img, gt),
               "ssim_skimage": ssim_skimage(img, gt)}
        row.update(_lpips_all(img, gt, lpips))
        per_view.append(row)
    keys = ["psnr", "ssim", "ssim_skimage"] + [k for k, _, _ in LPIPS_VARIANTS]
    mean = {k: (None if not per_view or any(r[k] is None for r in per_view)
                else float(np.mean([r[k] for r in per_view]))) for k in keys}
    return {**mean, "n_gaussians": trainer.n, "iterations": trainer.t,
            "train_seconds": round(trainer.train_seconds, 3), "n_test_views": len(per_view),
            "per_view": per_view}


def plot_history(history: dict, path: Path) -> None:
    """Train PSNR (per iteration and running mean) and test PSNR against iteration (Agg)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    t, p = np.asarray(history["train_t"]), np.asarray(history["train_psnr"], float)
    if len(t):
        ax.plot(t, p, color="0.8", lw=0.5, label="train PSNR (view of the iteration)")
        w = max(1, len(t) // 50)
        ax.plot(t[w - 1:], np.convolve(p, np.ones(w) / w, mode="valid"), color="C0",
                label=f"train PSNR, mean of {w}")
    if history["test_t"]:
        ax.plot(history["test_t"], history["test_psnr"], "o-", color="C3", label="test PSNR")
    ax.set_xlabel("iteration")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png")
    plt.close(fig)


def finish(run_dir: Path, trainer: Trainer, progress: bool = True) -> dict:
    """Model PLY, test renders, metrics.json, history.json and the PSNR plot (idempotent)."""
    cfg = trainer.cfg
    write_gaussians_ply(run_dir / MODEL_FILE, trainer.gaussians())
    if not trainer.history["test_t"] or trainer.history["test_t"][-1] != trainer.t:
        trainer.test_psnr()
    metrics = evaluate(trainer, cfg.lpips, run_dir / RENDER_DIR / "test")
    metrics["n_init_points"] = read_config(run_dir).get("n_init_points")
    metrics["peak_rss_gb"] = round(peak_rss_gb(), 3)
    atomic_write_json(run_dir / HISTORY_FILE, trainer.history)
    plot_history(trainer.history, run_dir / PLOT_FILE)
    atomic_write_json(run_dir / METRICS_FILE, metrics)
    if progress:
        print(metrics_table(metrics, run_dir))
    return metrics


def metrics_table(metrics: dict, run_dir: Path | None = None) -> str:
    fmt = lambda v: "n/a" if v is None else f"{v:.4f}"  # noqa: E731
    keys = ["psnr", "ssim", "ssim_skimage"] + [k for k, _, _ in LPIPS_VARIANTS]
    lines = [f"{'view':<24}" + "".join(f"{k:>20}" for k in keys)]
    for r in metrics["per_view"]:
        lines.append(f"{r['name']:<24}" + "".join(f"{fmt(r[k]):>20}" for k in keys))
    lines.append(f"{'mean':<24}" + "".join(f"{fmt(metrics[k]):>20}" for k in keys))
    lines.append(f"Gaussians {metrics['n_gaussians']}, iterations {metrics['iterations']}, "
                 f"train {metrics['train_seconds']:.1f} s" + (f", run {run_dir}" if run_dir else ""))
    return "\n".join(lines)


def eval_run(run_dir: str | Path, model: str | None = None, lpips: bool | None = None,
             progress: bool = True) -> dict:
    """Re-evaluate a finished run (the checkpoint's exact parameters, or ``model`` PLY)."""
    run_dir = Path(run_dir).absolute()
    config, cfg, trainer = _restore(run_dir)
    if model is not None:
        g = read_gaussians_ply(model, DTYPES[cfg.dtype])
        trainer.params = g.to_dict()
    elif trainer.t < cfg.iters:
        raise ConfigError(f"{run_dir}: the run stopped at iteration {trainer.t} of {cfg.iters}; "
                          f"finish it with: refgs train --resume {run_dir}")
    metrics = evaluate(trainer, cfg.lpips if lpips is None else lpips, run_dir / RENDER_DIR / "test")
    metrics["n_init_points"] = config.get("n_init_points")
    atomic_write_json(run_dir / METRICS_FILE, metrics)
    if progress:
        print(metrics_table(metrics, run_dir))
    return metrics


def render_run(run_dir: str | Path, split: str = "test") -> Path:
    """Clamped renders of the run's test and/or train views to RUN/renders/<split>/."""
    run_dir = Path(run_dir).absolute()
    _, _, trainer = _restore(run_dir)
    groups = {"test": trainer.test_views, "train": trainer.train_views}
    for name in (("test", "train") if split == "all" else (split,)):
        for v in groups[name]:
            atomic_save_png(run_dir / RENDER_DIR / name / (Path(v.name).stem + ".png"),
                            trainer.render_view(v))
    return run_dir / RENDER_DIR


def demo(out: str | Path | None = None, iters: int = DEMO_ITERS, progress: bool = True) -> dict:
    """Train DEMO_VIEWS views of the packaged demo scene and evaluate the held-out views."""
    from .data.demo import demo_scene_path

    out = Path(out) if out else Path(f"refgs-demo-{time.strftime('%Y%m%d-%H%M%S')}")
    cfg = TrainConfig.with_preset("dropgaussian", DEMO_DENSIFY, scene=str(demo_scene_path()),
                                  views=DEMO_VIEWS, iters=iters, images="images",
                                  init_points="train-views", checkpoint_every=0,
                                  eval_every=max(1, iters // 5))
    run_dir = train(cfg, out, progress=progress, command=["refgs", "demo"])
    return json.loads((run_dir / METRICS_FILE).read_text())


def _version() -> str:
    from . import __version__
    return __version__


# --- argument parsing -------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``refgs: error: ...``, exit 2) instead of usage + error."""

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="refgs", description="refgs: the numpy 3DGS specification - training CLI")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    t = sub.add_parser("train", help="train a new run, or continue one with --resume")
    t.add_argument("--resume", metavar="RUN_DIR", help="continue an interrupted run")
    t.add_argument("--scene", help="scene folder (sparse/0 + image folder)")
    t.add_argument("--images", default="images_8", help="image folder inside the scene")
    t.add_argument("--resolution", type=float, help="downsampling factor >= 1 applied on load")
    t.add_argument("--views", type=int, help="number of training views")
    t.add_argument("--method", default="3dgs", choices=sorted(METHODS))
    t.add_argument("--iters", type=int, help="iterations T (all schedule horizons use T)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--backend", default="reference", help=f"one of {available_backends()}")
    t.add_argument("--out", help="run directory to create")
    t.add_argument("--init-points", default="train-views", metavar="train-views|sfm-all|PATH.ply")
    t.add_argument("--checkpoint-every", type=int, default=1000, metavar="K", help="0: only on Ctrl-C")
    t.add_argument("--eval-every", type=int, metavar="K",
                   help="test PSNR every K (default T/10; 0: end only)")
    t.add_argument("--strict", action="store_true", help="unmatched images/model entries are errors")
    t.add_argument("--dtype", default="float64", choices=sorted(DTYPES))
    t.add_argument("--background", default="black", choices=sorted(BACKGROUNDS))
    t.add_argument("--loss-form", default="l1_plus", choices=LOSS_FORMS)
    t.add_argument("--lambda-dssim", type=float, default=0.2)
    t.add_argument("--no-clamp", action="store_true", help="do not clamp the render before the loss")
    t.add_argument("--profile", default="inria", choices=("inria", "gsplat"))
    t.add_argument("--sh-degree", type=int, default=3)
    t.add_argument("--holdout", type=int, default=8, help="every k-th view is a test view")
    t.add_argument("--triangulation", default="tuned", help="preset for --init-points train-views")
    t.add_argument("--no-lpips", action="store_true", help="skip LPIPS in the final evaluation")
    t.add_argument("--quiet", action="store_true", help="no progress bar or table")
    f = t.add_argument_group("flat-minima method (docs/spec/method.md) and DropGaussian")
    f.add_argument("--fm", action="store_true", help="add the flat-minima method (with --method dropgaussian: the plug-in)")
    f.add_argument("--fm-gamma", type=float, dest="gamma", help="perturbation coefficient (default 2)")
    f.add_argument("--fm-p", type=float, dest="p", help="perturbation probability (default 0.3)")
    f.add_argument("--fm-p-ramp", action="store_true", dest="p_ramp", default=None, help="ramp p as p t/T")
    f.add_argument("--fm-no-schedule", action="store_false", dest="schedule", default=None,
                   help="alpha(t) = 1 instead of t/T")
    f.add_argument("--fm-clamp", choices=CLAMP_MODES, dest="clamp", help="clamp reading (default axis)")
    f.add_argument("--fm-noise", choices=("anisotropic", "iso_max", "iso_mean", "iso_fixed"), dest="noise",
                   help="noise shape (ablation; iso_fixed: half the densification size threshold)")
    f.add_argument("--fm-noise-sigma", type=float, dest="noise_fixed_sigma",
                   help="with --fm-noise iso_fixed: this standard deviation instead")
    f.add_argument("--fm-perturb", choices=PERTURB_TARGETS, dest="perturb",
                   help="perturbed parameter (ablation; default position)")
    f.add_argument("--fm-mixed-loss", action="store_true", dest="mixed_loss", default=None,
                   help="ablation: average the gradients of a fully perturbed and a clean render")
    f.add_argument("--fm-no-reinit", action="store_false", dest="reinit", default=None, help="no periodic reinit")
    f.add_argument("--fm-reinit-interval", type=int, dest="reinit_interval")
    f.add_argument("--fm-reinit-window", type=int, dest="reinit_window")
    f.add_argument("--drop-r-max", type=float, dest="r_max", help="DropGaussian's largest drop rate (0.2)")
    d = t.add_argument_group("densification")
    d.add_argument("--densify-preset", default="dropgaussian", choices=sorted(DENSIFY_PRESETS))
    d.add_argument("--densify-from", type=int, dest="start")
    d.add_argument("--densify-interval", type=int, dest="interval")
    d.add_argument("--densify-until", type=int, dest="until")
    d.add_argument("--densify-grad-threshold", type=float, dest="grad_threshold")
    d.add_argument("--opacity-reset-interval", type=int, dest="opacity_reset_interval")
    d.add_argument("--screen-size-rule", choices=SCREEN_SIZE_RULES, dest="screen_size_rule")

    e = sub.add_parser("eval", help="evaluate a finished run on its test views")
    e.add_argument("run_dir")
    e.add_argument("--model", help="evaluate this 3DGS PLY instead of the run's parameters")
    e.add_argument("--no-lpips", action="store_true")
    e.add_argument("--quiet", action="store_true")

    r = sub.add_parser("render", help="render a run's views to PNG")
    r.add_argument("run_dir")
    r.add_argument("--split", default="test", choices=("test", "train", "all"))

    m = sub.add_parser("demo", help="train 3 views of the packaged demo scene and evaluate")
    m.add_argument("--out")
    m.add_argument("--iters", type=int, default=DEMO_ITERS)
    m.add_argument("--quiet", action="store_true")

    from .bench import add_parser as _add_bench
    from .figures import add_parser as _add_figures
    from .flatness import add_parser as _add_flatness
    from .records import add_parser as _add_record
    from .tables import add_parser as _add_table
    _add_bench(sub)
    _add_flatness(sub)
    _add_table(sub)
    _add_figures(sub)
    _add_record(sub)
    return p


_NEW_RUN_FLAGS = ("scene", "views", "iters", "out")
_DENSIFY_FLAGS = ("start", "interval", "until", "grad_threshold", "opacity_reset_interval",
                  "screen_size_rule")
_METHOD_FLAGS = ("gamma", "p", "p_ramp", "schedule", "clamp", "noise", "noise_fixed_sigma", "perturb",
                 "mixed_loss", "reinit", "reinit_interval",
                 "reinit_window", "r_max")


def method_params_from_args(args) -> dict:
    """Every parameter of the chosen method with its value (recorded in config.json, DG-02)."""
    from .methods.training import make_method
    given = {k: getattr(args, k) for k in _METHOD_FLAGS if getattr(args, k, None) is not None}
    if args.fm:
        given["fm"] = True
    fm_used = args.method == "fm" or args.fm
    if not fm_used and any(k not in ("r_max", "fm") for k in given):
        raise ConfigError("--fm-*: flat-minima options need --method fm or --fm")
    if args.method != "dropgaussian" and "r_max" in given:
        raise ConfigError("--drop-r-max: only with --method dropgaussian")
    method = make_method(args.method, fm=bool(args.fm), **_split_method_params(given))
    full = dict(getattr(method, "params_dict", dict)())
    params = {k[3:]: v for k, v in full.items() if k.startswith("fm_")}
    if "drop_r_max" in full:
        params["r_max"] = full["drop_r_max"]
    if args.fm:
        params["fm"] = True
    return params


def _split_method_params(given: dict) -> dict:
    from .methods.training import FlatMinimaConfig
    fm_cfg = {k: v for k, v in given.items() if k not in ("fm", "r_max")}
    out = {"fm_config": FlatMinimaConfig(**fm_cfg)}
    if "r_max" in given:
        out["r_max"] = given["r_max"]
    return out


def config_from_args(args) -> TrainConfig:
    """TrainConfig of a new run from parsed ``refgs train`` arguments."""
    for flag in _NEW_RUN_FLAGS:
        if getattr(args, flag) is None:
            raise ConfigError(f"--{flag}: required for a new run (or give --resume RUN_DIR)")
    return TrainConfig.with_preset(
        args.densify_preset, {k: getattr(args, k) for k in _DENSIFY_FLAGS},
        scene=args.scene, views=args.views, iters=args.iters, seed=args.seed, images=args.images,
        resolution=args.resolution, method=args.method, method_params=method_params_from_args(args),
        backend=args.backend,
        init_points=args.init_points, checkpoint_every=args.checkpoint_every,
        eval_every=args.eval_every, strict=args.strict, dtype=args.dtype, profile=args.profile,
        sh_degree=args.sh_degree, background=args.background, loss_form=args.loss_form,
        lambda_dssim=args.lambda_dssim, clamp_render=not args.no_clamp, holdout=args.holdout,
        triangulation=args.triangulation, lpips=not args.no_lpips)


def _train_command(args, argv) -> Path:
    if args.resume:
        given = [f for f in _NEW_RUN_FLAGS if getattr(args, f) is not None]
        if given:
            raise ConfigError(f"--resume: takes its settings from the run's {CONFIG_FILE}; do not "
                              f"also give --{given[0]}")
        return resume(args.resume, progress=not args.quiet)
    cfg = config_from_args(args)
    return train(cfg, args.out, progress=not args.quiet, command=["refgs", *argv])


def _one_line(message) -> str:
    return " ".join(str(message).split())


def main(argv: list | None = None) -> int:
    """Entry point ``refgs`` (console script refgs.cli:main)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    old_show = warnings.showwarning
    warnings.showwarning = lambda msg, cat, *a, **k: print(
        f"refgs: warning: {_one_line(msg)}", file=sys.stderr)
    try:
        if args.command == "train":
            run_dir = _train_command(args, argv)
            if not args.quiet:
                print(f"run directory: {run_dir}")
        elif args.command == "eval":
            eval_run(args.run_dir, args.model, False if args.no_lpips else None, not args.quiet)
        elif args.command == "render":
            print(render_run(args.run_dir, args.split))
        elif args.command == "demo":
            demo(args.out, args.iters, progress=not args.quiet)
        elif args.command == "bench":
            from .bench import run as bench_run
            bench_run(args)
        elif args.command == "flatness":
            from .flatness import run as flatness_run
            flatness_run(args)
        elif args.command == "table":
            from .tables import run as table_run
            table_run(args)
        elif args.command == "figures":
            from .figures import run as figures_run
            figures_run(args)
        elif args.command == "record":
            from .records import run as record_run
            record_run(args)
        return 0
    except RefgsError as exc:
        print(f"refgs: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Interrupted as exc:
        print(f"refgs: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("refgs: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:
        print(f"refgs: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        warnings.showwarning = old_show


__all__ = ["main", "build_parser", "train", "resume", "eval_run", "render_run", "demo",
           "evaluate", "finish", "Interrupted", "StopFlag", "load_views", "config_from_args"]
