"""The run directory: create, train, resume, load, evaluate and render a run (docs/spec/training.md
TRN-07..TRN-09).  The one way in: ``refgs train|eval|render`` and ``refgs demo`` call these functions, and the
analysis floor (refgs.analysis) reads runs through them.

A run directory holds (the *_FILE names below):

    config.json       every setting, the train/test views, provenance, the resumes
    checkpoint.npz    the trainer's full state (refgs.train.checkpoint: plain arrays, no pickle)
    init_points.ply   the initial point cloud
    model.ply         the trained Gaussians (3DGS PLY)
    metrics.json      metrics of the test views; history.json the per-iteration curves
    psnr.png          the PSNR curves;  renders/<split>/ clamped renders of the views

It is built under a hidden name beside its final path and renamed to it at the first checkpoint
(or at the end); a run that fails before that leaves nothing behind (TRN-09).

    train(cfg, out) -> Path            a new run
    resume(path) -> Path               continue an interrupted run exactly
    load(path) -> LoadedRun            (config, cfg, trainer) with the checkpoint loaded
    evaluate_run(path) -> dict         re-evaluate a finished run (writes metrics.json)
    render_run(path, split) -> Path    PNG renders of its views
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import signal
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from . import __version__
from .backends import get_backend
from .errors import ConfigError
from .io.atomic import (atomic_path, atomic_save_png, atomic_write_json, partial_dir,
                        publish_dir)
from .io.ply import read_gaussians_ply, write_gaussians_ply
from .methods import METHOD_NAMES, make_method
from .train.checkpoint import (CheckpointError, load_checkpoint, peak_rss_gb, provenance,
                               save_checkpoint, source_hash)
from .train.schedule import scene_extent
from .train.trainer import DTYPES, TrainConfig, Trainer, View

#: Files of a run directory.
CONFIG_FILE = "config.json"
CHECKPOINT_FILE = "checkpoint.npz"
MODEL_FILE = "model.ply"
INIT_FILE = "init_points.ply"
METRICS_FILE = "metrics.json"
HISTORY_FILE = "history.json"
PLOT_FILE = "psnr.png"
RENDER_DIR = "renders"
#: Tag of the hidden folder a run is built in before it is published (``.<name>.partial-XXXX``).
PARTIAL_TAG = ".partial-"
#: Smallest image side LPIPS accepts (refgs.metrics.lpips docstring: vgg >= 16, alex >= 31).
LPIPS_MIN_SIDE = {"vgg": 16, "alex": 31}
#: The three LPIPS variants reported: (key, net, input convention) (MET-05, MET-06).
LPIPS_VARIANTS = (("lpips_vgg", "vgg", "01"), ("lpips_vgg_official", "vgg", "official"),
                  ("lpips_alex", "alex", "official"))


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


class RunDir:
    """Where a run writes: ``path`` (the hidden partial folder until published, then ``final``).

    create(final)  a new partial folder beside ``final``; ConfigError (--out) if ``final`` exists
    existing(path) a published run directory
    publish()      rename to the final path (idempotent)
    discard()      remove the folder if it was never published
    """

    def __init__(self, final: Path, path: Path, published: bool):
        self.final, self.path, self.published = Path(final), Path(path), published

    @staticmethod
    def create(final: str | Path) -> "RunDir":
        final = Path(final).absolute()
        if final.exists():
            raise ConfigError(f"--out: {final} already exists (choose a new folder, or continue "
                              f"it with: refgs train --resume {final})")
        if not final.parent.is_dir():
            raise ConfigError(f"--out: parent folder {final.parent} does not exist")
        return RunDir(final, partial_dir(final, PARTIAL_TAG), False)

    @staticmethod
    def existing(path: str | Path) -> "RunDir":
        path = Path(path).absolute()
        return RunDir(path, path, True)

    def publish(self) -> None:
        if self.published:
            return
        try:
            publish_dir(self.path, self.final)
        except FileExistsError:
            raise ConfigError(f"--out: {self.final} appeared while the run was being built; "
                              f"the run is kept in {self.path}") from None
        self.path, self.published = self.final, True

    def discard(self) -> None:
        if not self.published:
            shutil.rmtree(self.path, ignore_errors=True)

    def __truediv__(self, name: str) -> Path:
        return self.path / name


def read_config(run_dir: str | Path) -> dict:
    """The config.json of a run directory; CheckpointError naming the file when absent/corrupt."""
    path = Path(run_dir) / CONFIG_FILE
    if not Path(run_dir).is_dir():
        raise CheckpointError(f"{run_dir}: run directory not found")
    if not path.is_file():
        raise CheckpointError(f"{path}: not found (is {run_dir} a refgs run directory?)")
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path}: not valid JSON ({exc})") from None


def write_config(run: RunDir, config: dict) -> Path:
    return atomic_write_json(run / CONFIG_FILE, config)


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
    """sha256 (16 hex digits) of the settings' canonical JSON: a checkpoint carries it, so that a
    config.json edited after the run started is refused (TRN-09)."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


# --- the loop with checkpoints --------------------------------------------------------------------
def make_trainer(cfg: TrainConfig, train_views, test_views, params: dict,
                 backend: str | None = None) -> Trainer:
    """A trainer for ``cfg`` with its method and its backend (``backend``: another registry name
    or module:object to render with instead of the run's, e.g. for an analysis)."""
    extent = scene_extent([v.camera.center for v in train_views])
    if extent == 0.0:
        warnings.warn("one training view: scene extent 0, positions will not move (as in 3DGS)",
                      stacklevel=2)
    renderer = get_backend(backend or cfg.backend, cfg.profile, cfg.dtype)
    return Trainer(cfg, train_views, test_views, params, extent, renderer,
                   make_method(cfg.method, cfg.method_params))


def _checkpoint(trainer: Trainer, run: RunDir) -> None:
    meta = trainer.state_meta()
    meta["settings_hash"] = settings_hash(trainer.cfg.to_dict())
    save_checkpoint(run / CHECKPOINT_FILE, trainer.state_arrays(), meta)
    run.publish()


def is_test_point(t: int, every: int, iters: int) -> bool:
    """Whether the loop measures the test PSNR at the end of iteration t (TRN-07): at the
    iteration *before* each multiple of ``every`` (0: none), so that the opacity reset (TRN-06)
    and FM's reinitialisation (FM-06), which fall on multiples, never show in the curve; the
    final iteration T is measured after the loop (so T - 1 is not, when T is a multiple)."""
    return bool(every) and (t + 1) % every == 0 and t + 1 < iters


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
                if is_test_point(t, cfg.eval_interval, cfg.iters):
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


def train(cfg: TrainConfig, out: str | Path, progress: bool = True, callback=None,
          command: list | None = None) -> Path:
    """Start a new run in ``out`` (TRN-07..TRN-09); returns the run directory.  ``callback
    (trainer, stop_flag)`` is called after every iteration (tests stop or inspect runs with it)."""
    from .data.init import init_gaussians_from_points
    from .data.pointcloud import write_ply

    cfg = absolute_paths(cfg).validate(METHOD_NAMES)
    get_backend(cfg.backend, cfg.profile, cfg.dtype)
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
        trainer = make_trainer(cfg, train_views, test_views, g.to_dict())
        trainer.init_cloud = {"points": np.asarray(points), "colors": np.asarray(colors)}
        write_config(run, {
            "refgs_version": __version__, "command": command, "settings": cfg.to_dict(),
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


class LoadedRun(NamedTuple):
    """A run directory read back: its config.json, its TrainConfig, and a trainer holding the
    checkpoint's exact state (parameters, optimiser, random streams, history)."""

    config: dict
    cfg: TrainConfig
    trainer: Trainer


def load(run_dir: str | Path, backend: str | None = None) -> LoadedRun:
    """The run in ``run_dir`` with its checkpoint loaded (the run may be unfinished);
    CheckpointError naming the file when the config, the checkpoint or the scene disagree.
    ``backend``: render with this backend instead of the run's."""
    run_dir = Path(run_dir).absolute()
    config = read_config(run_dir)
    try:
        cfg = TrainConfig.from_dict(config["settings"]).validate(METHOD_NAMES)
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
    trainer = make_trainer(cfg, train_views, test_views, params, backend)
    trainer.load_state(arrays, meta)
    return LoadedRun(config, cfg, trainer)


def resume(run_dir: str | Path, progress: bool = True, callback=None) -> Path:
    """Continue an interrupted run to its --iters (TRN-09); a finished run is only completed
    (outputs written if missing)."""
    from .data.pointcloud import write_ply

    run = RunDir.existing(run_dir)
    config, cfg, trainer = load(run.path)
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
    """The metrics as a fixed-width text table, one row per test view and the mean."""
    fmt = lambda v: "n/a" if v is None else f"{v:.4f}"  # noqa: E731
    keys = ["psnr", "ssim", "ssim_skimage"] + [k for k, _, _ in LPIPS_VARIANTS]
    lines = [f"{'view':<24}" + "".join(f"{k:>20}" for k in keys)]
    for r in metrics["per_view"]:
        lines.append(f"{r['name']:<24}" + "".join(f"{fmt(r[k]):>20}" for k in keys))
    lines.append(f"{'mean':<24}" + "".join(f"{fmt(metrics[k]):>20}" for k in keys))
    lines.append(f"Gaussians {metrics['n_gaussians']}, iterations {metrics['iterations']}, "
                 f"train {metrics['train_seconds']:.1f} s" + (f", run {run_dir}" if run_dir else ""))
    return "\n".join(lines)


def evaluate_run(run_dir: str | Path, model: str | None = None, lpips: bool | None = None,
                 progress: bool = True) -> dict:
    """Re-evaluate a finished run (the checkpoint's exact parameters, or ``model`` PLY)."""
    run_dir = Path(run_dir).absolute()
    config, cfg, trainer = load(run_dir)
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
    trainer = load(run_dir).trainer
    groups = {"test": trainer.test_views, "train": trainer.train_views}
    for name in (("test", "train") if split == "all" else (split,)):
        for v in groups[name]:
            atomic_save_png(run_dir / RENDER_DIR / name / (Path(v.name).stem + ".png"),
                            trainer.render_view(v))
    return run_dir / RENDER_DIR


__all__ = ["train", "resume", "load", "LoadedRun", "make_trainer", "evaluate", "evaluate_run",
           "render_run", "finish", "metrics_table", "plot_history", "load_views",
           "initial_points", "absolute_paths", "settings_hash", "is_test_point", "read_config", "write_config",
           "RunDir", "Interrupted", "StopFlag", "CONFIG_FILE", "CHECKPOINT_FILE", "MODEL_FILE",
           "INIT_FILE", "METRICS_FILE", "HISTORY_FILE", "PLOT_FILE", "RENDER_DIR"]
