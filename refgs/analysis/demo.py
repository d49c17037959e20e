"""`refgs demo`: vanilla 3DGS against flat-minima training (FM) on the same sparse views.

What a newcomer runs first (README).  It needs no data: the packaged demo scene
(refgs.data.demo, a textured room corner rendered from known cameras and reconstructed with
pycolmap) is built on first use.  Both methods train DEMO_VIEWS of its views from the same
train-view point cloud and seed, through ``refgs.runs.train``; the held-out views are evaluated
(PSNR / SSIM / LPIPS) and one picture is written:

    DIR/comparison.png   a held-out view: ground truth | 3DGS | FM (each with its PSNR),
                         and the test PSNR of both against iteration
    DIR/3dgs/, DIR/fm/   the two run directories (refgs.runs; ``refgs eval`` / ``refgs render``)

The fast backend (refgs.fast) is used whenever numba is installed, else the numpy reference
(about 20 times slower; DEMO_ITERS_REFERENCE iterations unless ``--iters`` says otherwise).

Test PSNR is recorded every T/20 iterations, at the iteration *before* each multiple, as every
run measures it (refgs.runs.is_test_point, TRN-07): FM re-initialises the Gaussians' shape and
resets their opacity at multiples of its re-initialisation interval (paper, Method;
refgs.methods.flat_minima_method), so a test render taken just after one shows the reset, not
what training has reached.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..backends import default_backend
from ..errors import ConfigError
from ..io.atomic import atomic_path
from ..methods import method_params
from ..train.trainer import TrainConfig
from .. import runs

#: sparse views trained (the paper's 3-view LLFF setting)
DEMO_VIEWS = 3
#: iterations of each of the two runs (both together took 90 s on 2 cores with the fast backend,
#: scene generation included; README)
DEMO_ITERS = 1000
#: the same without numba (the numpy reference is about 20 times slower: a few minutes)
DEMO_ITERS_REFERENCE = 200
#: the two methods compared, in the picture's order
DEMO_METHODS = ("3dgs", "fm")
#: The paper's 10k-iteration protocol (DropGaussian's schedule, docs/spec/training.md; the FM
#: re-initialisation of the paper's Method) as fractions of the run's length T, so that a demo
#: of any length is that protocol compressed: densify from T/20 every T/100, opacity reset every
#: 3T/10, FM re-initialisation every T/10 with a T/100 frozen window; test PSNR every T/20.
PROTOCOL_ITERS = 10_000
PROTOCOL_SCHEDULE = {"start": 500, "interval": 100, "opacity_reset_interval": 3000,
                     "reinit_interval": 1000, "reinit_window": 100, "eval_every": 500}
#: the demo scene's image size (refgs.data.demo; larger than the notebooks' 160 x 120 so that
#: the renders show detail)
DEMO_SCENE_SIZE = (200, 150)
#: the picture
FIGURE_FILE = "comparison.png"
#: the held-out view shown (index into the test views)
SHOWN_VIEW = 0


def demo_schedule(iters: int) -> dict:
    """PROTOCOL_SCHEDULE scaled to ``iters`` iterations (each at least 1)."""
    return {k: max(1, round(v * iters / PROTOCOL_ITERS)) for k, v in PROTOCOL_SCHEDULE.items()}


def demo_config(method: str, scene: str, iters: int, backend: str, seed: int) -> TrainConfig:
    """The TrainConfig of one demo run (``method`` one of DEMO_METHODS)."""
    if method not in DEMO_METHODS:
        raise ConfigError(f"demo method: expected one of {DEMO_METHODS}, got {method!r}")
    sched = demo_schedule(iters)
    densify = {k: sched[k] for k in ("start", "interval", "opacity_reset_interval")}
    given = ({k: sched[k] for k in ("reinit_interval", "reinit_window")} if method == "fm"
             else {})
    return TrainConfig.with_preset(
        "dropgaussian", densify, scene=scene, views=DEMO_VIEWS, iters=iters, seed=seed,
        images="images", method=method, method_params=method_params(method, given),
        backend=backend, init_points="train-views", checkpoint_every=0,
        eval_every=sched["eval_every"])


def comparison_figure(run_dirs: dict, path: Path, view: int = SHOWN_VIEW) -> Path:
    """``path``: held-out view ``view`` as ground truth | one render per run (its PSNR in the
    title), and below the test PSNR of every run against iteration.  ``run_dirs``: label ->
    finished run directory (its renders/test PNGs, metrics.json and history.json)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    labels = list(run_dirs)
    first = runs.load(run_dirs[labels[0]])
    gt_view = first.trainer.test_views[view]
    name = Path(gt_view.name).stem
    fig = plt.figure(figsize=(3.2 * (len(labels) + 1), 6.2), dpi=110)
    grid = fig.add_gridspec(2, len(labels) + 1, height_ratios=(1.0, 0.8))
    panels = [("ground truth (held out)", np.clip(gt_view.image, 0, 1))]
    for label in labels:
        metrics = json.loads((Path(run_dirs[label]) / runs.METRICS_FILE).read_text())
        psnr = metrics["per_view"][view]["psnr"]
        img = np.asarray(Image.open(Path(run_dirs[label]) / runs.RENDER_DIR / "test"
                                    / f"{name}.png"), np.float64) / 255.0
        panels.append((f"{label}: {psnr:.2f} dB", img))
    for k, (title, img) in enumerate(panels):
        ax = fig.add_subplot(grid[0, k])
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    ax = fig.add_subplot(grid[1, :])
    for k, label in enumerate(labels):
        h = json.loads((Path(run_dirs[label]) / runs.HISTORY_FILE).read_text())
        m = json.loads((Path(run_dirs[label]) / runs.METRICS_FILE).read_text())
        ax.plot(h["test_t"], h["test_psnr"], "o-", ms=3, color=f"C{k}",
                label=f"{label}: final {m['psnr']:.2f} dB (mean of {m['n_test_views']} "
                      f"held-out views)")
    ax.set_xlabel("iteration")
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9, loc="lower right")
    fig.suptitle(f"{DEMO_VIEWS} training views, held-out view {name}", fontsize=11)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png")
    plt.close(fig)
    return path


def summary_table(metrics: dict) -> str:
    """label -> metrics.json as a text table: PSNR, SSIM, LPIPS-VGG, Gaussians, seconds."""
    fmt = lambda v, d: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    lines = [f"{'method':<8}{'PSNR dB':>10}{'SSIM':>8}{'LPIPS':>8}{'Gaussians':>11}{'train s':>9}"]
    for label, m in metrics.items():
        lines.append(f"{label:<8}{fmt(m['psnr'], 2):>10}{fmt(m['ssim'], 3):>8}"
                     f"{fmt(m['lpips_vgg'], 3):>8}{m['n_gaussians']:>11}"
                     f"{m['train_seconds']:>9.1f}")
    return "\n".join(lines)


def run_demo(out: str | Path | None = None, iters: int | None = None,
             backend: str | None = None, seed: int = 0, progress: bool = True) -> dict:
    """Train DEMO_METHODS on DEMO_VIEWS views of the demo scene into ``out`` (default
    ``refgs-demo-<time>``), write the comparison picture and print the table.  Returns
    {"metrics": label -> metrics.json, "figure": path, "seconds": wall time}."""
    from ..data.demo import demo_scene_path

    t0 = time.perf_counter()
    backend = backend or default_backend()
    if iters is None:
        iters = DEMO_ITERS if backend == "fast" else DEMO_ITERS_REFERENCE
    out = Path(out) if out else Path(f"refgs-demo-{time.strftime('%Y%m%d-%H%M%S')}")
    if progress:
        print(f"refgs demo: {DEMO_VIEWS} views of the packaged scene, {iters} iterations of "
              f"{' and '.join(DEMO_METHODS)}, backend {backend}")
    scene = str(demo_scene_path(*DEMO_SCENE_SIZE))
    out.mkdir(parents=True, exist_ok=True)
    dirs, metrics = {}, {}
    for method in DEMO_METHODS:
        cfg = demo_config(method, scene, iters, backend, seed)
        dirs[method] = runs.train(cfg, out / method, progress=progress, command=["refgs", "demo"])
        metrics[method] = json.loads((dirs[method] / runs.METRICS_FILE).read_text())
    figure = comparison_figure(dirs, out / FIGURE_FILE)
    seconds = time.perf_counter() - t0
    if progress:
        print(summary_table(metrics))
        print(f"picture: {figure}\nrun directories: {', '.join(str(d) for d in dirs.values())}"
              f"\ntook {seconds:.0f} s")
    return {"metrics": metrics, "figure": figure, "seconds": seconds}


__all__ = ["run_demo", "demo_config", "demo_schedule", "comparison_figure", "summary_table",
           "DEMO_VIEWS", "DEMO_ITERS", "DEMO_ITERS_REFERENCE", "DEMO_METHODS", "PROTOCOL_ITERS",
           "PROTOCOL_SCHEDULE", "DEMO_SCENE_SIZE", "FIGURE_FILE"]
