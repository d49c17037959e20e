"""Qualitative comparison per scene: ground truth | 3DGS | DropGaussian | FM on one test view,
with a magnified crop where the methods' renders differ most (FM-14).

    refgs figures --compare RUN_DIR [RUN_DIR ...] [--seed 0] [--view 0] [--out figures]
    python -m refgs.analysis.qualitative RUN_DIR [RUN_DIR ...] [--seed 0] [--view 0] [--out figures]

Runs are grouped by (scene folder name, views); within a group the runs of seed ``--seed`` are
compared, one column per method label (``METHOD_ORDER`` first, any other label after, sorted).
The view is the ``--view``-th name of config.json's ``test_images`` (the same list for every run
of a group).  Renders are read from ``RUN/renders/test/<view>.png`` (written when a run
finishes, or by ``refgs render RUN``); the ground truth is loaded from the scene in the run's
config.json.  The crop is the ``CROP_SIZE`` square (clipped to the image) with the largest sum
of the per-pixel variance across the methods' renders (mean over channels): chosen from the
renders alone, not from their errors; with one method, its largest squared error instead.

One PNG per group, ``compare_<scene>_v<views>_s<seed>.png``: the full images with the crop's box
on top, the crops below (nearest-neighbour magnification), each render titled with its PSNR
on the view.
"""
from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, RefgsError
from ..io.atomic import atomic_path
from ..runs import CONFIG_FILE, RENDER_DIR
from .tables import method_label, read_run_json

#: Side of the crop in pixels (our choice: an eighth of the 504-pixel width of LLFF images_8).
CROP_SIZE = 64
#: Column order of the methods (the paper's: baseline, DropGaussian, FM).
METHOD_ORDER = ("3dgs", "dropgaussian", "fm")
#: Column titles of the method labels.
DISPLAY = {"3dgs": "3DGS", "dropgaussian": "DropGaussian", "fm": "FM"}
#: Colour of the crop's box.
BOX_COLOR = "yellow"
DEFAULT_OUT = "figures"


@dataclass
class CompareRun:
    """One run of a comparison: its folder, settings, method label and test view names."""

    dir: Path
    settings: dict
    label: str
    seed: int
    test_images: list


def load_compare_run(run_dir: str | Path) -> CompareRun:
    """The CompareRun of a run directory; ConfigError naming the file."""
    run_dir = Path(run_dir).absolute()
    config = read_run_json(run_dir / CONFIG_FILE)
    s = config.get("settings")
    names = config.get("test_images")
    if not isinstance(s, dict) or not isinstance(names, list) or not names:
        raise ConfigError(f"{run_dir / CONFIG_FILE}: expected 'settings' and 'test_images'")
    try:
        return CompareRun(run_dir, s, method_label(s), int(s["seed"]), names)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{run_dir / CONFIG_FILE}: settings lack seed ({exc})") from None


def group_runs(runs: list[CompareRun], seed: int) -> dict[tuple, list[CompareRun]]:
    """{(scene, views): runs of ``seed`` in column order}; ConfigError when no run has the seed,
    when two runs of a group share a method label or disagree on the test views."""
    groups: dict = {}
    for r in runs:
        if r.seed == seed:
            key = (Path(r.settings["scene"]).name, int(r.settings["views"]))
            groups.setdefault(key, []).append(r)
    if not groups:
        raise ConfigError(f"--seed {seed}: none of the {len(runs)} runs has this seed")
    order = {m: k for k, m in enumerate(METHOD_ORDER)}
    for key, rs in groups.items():
        rs.sort(key=lambda r: (order.get(r.label, len(order)), r.label))
        for a, b in zip(rs, rs[1:]):
            if a.label == b.label:
                raise ConfigError(f"{b.dir}: same scene, views, method ({a.label}) and seed as "
                                  f"{a.dir}")
            if a.test_images != b.test_images:
                raise ConfigError(f"{b.dir}: test views {b.test_images} differ from {a.dir}'s")
    return groups


def render_path(run: CompareRun, view: int) -> Path:
    """The saved render of the ``view``-th test view; ConfigError if out of range or missing."""
    if not 0 <= view < len(run.test_images):
        raise ConfigError(f"--view {view}: {run.dir} has {len(run.test_images)} test views")
    png = run.dir / RENDER_DIR / "test" / (Path(run.test_images[view]).stem + ".png")
    if not png.is_file():
        raise ConfigError(f"{png}: not found (render it with: refgs render {run.dir})")
    return png


def read_png(path: Path) -> np.ndarray:
    """An RGB PNG as (H, W, 3) float64 in [0, 1]."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), np.float64) / 255.0


def ground_truth(settings: dict, name: str, cache: dict) -> np.ndarray:
    """(H, W, 3) ground truth of the test view ``name`` of the run's scene (refgs.runs.load_views);
    ``cache`` keeps the test views per scene setting."""
    from ..runs import load_views
    from ..train.trainer import TrainConfig

    cfg = TrainConfig.from_dict(settings)
    key = (cfg.scene, cfg.images, cfg.resolution, cfg.views, cfg.holdout, cfg.dtype)
    if key not in cache:
        cache[key] = {v.name: np.asarray(v.image, np.float64) for v in load_views(cfg)[4]}
    if name not in cache[key]:
        raise ConfigError(f"{cfg.scene}: no test view {name} (views {sorted(cache[key])})")
    return cache[key][name]


def crop_window(renders: list[np.ndarray], gt: np.ndarray, size: int = CROP_SIZE) -> tuple:
    """(y0, x0, h, w) of the ``size`` square (clipped to the (H, W) image) with the largest sum
    of the across-render variance (mean over channels), or with one render of its squared error
    against ``gt``; the first such window in row-major order on ties."""
    stack = np.stack(renders)                                    # (M, H, W, 3)
    score = (stack.var(axis=0) if len(renders) > 1 else (stack[0] - gt) ** 2).mean(axis=2)
    h, w = min(size, score.shape[0]), min(size, score.shape[1])
    ii = np.pad(score.cumsum(0).cumsum(1), ((1, 0), (1, 0)))    # summed-area table
    sums = ii[h:, w:] - ii[:-h, w:] - ii[h:, :-w] + ii[:-h, :-w]
    y0, x0 = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(y0), int(x0), h, w


def plot_comparison(key: tuple, runs: list[CompareRun], view: int, path: Path,
                    cache: dict) -> str:
    """Draw one group's figure to ``path``; returns the line of index.md describing it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from ..metrics.psnr import psnr

    name = runs[0].test_images[view]
    imgs = [read_png(render_path(r, view)) for r in runs]
    gt = ground_truth(runs[0].settings, name, cache)
    for r, img in zip(runs, imgs):
        if img.shape != gt.shape:
            raise ConfigError(f"{render_path(r, view)}: {img.shape[1]}x{img.shape[0]} render, but "
                              f"the view {name} is {gt.shape[1]}x{gt.shape[0]}")
    y0, x0, h, w = crop_window(imgs, gt)
    cols = [("ground truth", gt)]
    cols += [(f"{DISPLAY.get(r.label, r.label)}\nPSNR {psnr(img, gt):.2f} dB", img)
             for r, img in zip(runs, imgs)]
    H, W = gt.shape[:2]
    fig, axes = plt.subplots(2, len(cols), figsize=(3.2 * len(cols), 3.2 * H / W + 3.2 + 0.8),
                             squeeze=False)
    for k, (title, img) in enumerate(cols):
        axes[0][k].imshow(np.clip(img, 0, 1))
        axes[0][k].add_patch(Rectangle((x0 - 0.5, y0 - 0.5), w, h, fill=False, lw=1.2,
                                       edgecolor=BOX_COLOR))
        axes[0][k].set_title(title, fontsize=9)
        axes[1][k].imshow(np.clip(img[y0:y0 + h, x0:x0 + w], 0, 1), interpolation="nearest")
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    scene, views = key
    seed = runs[0].seed
    fig.suptitle(f"{scene}, {views} views, seed {seed}, test view {name}: {w}x{h} crop at "
                 f"x={x0}, y={y0}, where the renders differ most", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
    return (f"`{path.name}`: {scene} {views} views, seed {seed}, test view {name}: ground truth | "
            + " | ".join(r.label for r in runs) + " (" + ", ".join(str(r.dir) for r in runs) + ")")


def comparison_name(key: tuple, seed: int) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", f"compare_{key[0]}_v{key[1]}_s{seed}.png")


def plan(run_dirs, seed: int = 0, view: int = 0) -> dict[tuple, list[CompareRun]]:
    """The groups of ``group_runs``, every render checked present (nothing written)."""
    if not run_dirs:
        raise ConfigError("--compare: give at least one RUN_DIR")
    groups = group_runs([load_compare_run(d) for d in run_dirs], seed)
    for rs in groups.values():
        for r in rs:
            render_path(r, view)
    return groups


def make_comparisons(groups: dict, out: str | Path, seed: int = 0, view: int = 0,
                     cache: dict | None = None) -> list[tuple[Path, str]]:
    """One figure per group of ``plan`` into ``out``; [(file, index.md line)]."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cache = {} if cache is None else cache
    written = []
    for key, rs in sorted(groups.items()):
        path = out / comparison_name(key, seed)
        written.append((path, plot_comparison(key, rs, view, path, cache)))
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m refgs.analysis.qualitative",
                                 description="ground truth | 3DGS | DropGaussian | FM per scene")
    ap.add_argument("run_dirs", nargs="+")
    ap.add_argument("--seed", type=int, default=0, help="the seed of the runs compared (default 0)")
    ap.add_argument("--view", type=int, default=0, help="index into the test views (default 0)")
    ap.add_argument("--out", default=DEFAULT_OUT, help="folder (default figures/, git-ignored)")
    args = ap.parse_args(argv)
    try:
        for path, _ in make_comparisons(plan(args.run_dirs, args.seed, args.view), args.out,
                                        args.seed, args.view):
            print(path)
    except RefgsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


__all__ = ["CROP_SIZE", "METHOD_ORDER", "CompareRun", "load_compare_run", "group_runs", "plan",
           "crop_window", "ground_truth", "make_comparisons", "main"]

if __name__ == "__main__":
    sys.exit(main())
