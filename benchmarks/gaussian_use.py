"""How many of a trained run's Gaussians the training views actually use.

    python benchmarks/gaussian_use.py RUN [RUN ...]

For each run directory (its ``checkpoint.npz``, finished or not) every training view is rendered
with ``refgs.fast`` at the full SH degree, and each Gaussian's blended fragments are counted
(power <= 0, alpha >= 1/255, before the pixel's stop: the fragments the compositing blends,
RAS-03..RAS-06) together with its total blending weight a T summed over the views.  A Gaussian
with no blended fragment in any training view receives no photometric gradient and only costs
time (projection, tile lists, Adam); one with a total weight below ``TINY_WEIGHT`` per view
changes no pixel by more than that.  The report says how many there are and how many of the
tile-list intersections they hold: the work densification creates without effect.
"""
from __future__ import annotations

import argparse
import warnings

import numpy as np
from fragments import blended_fragments        # benchmarks/fragments.py (run as a script)

#: total blending weight per training view below which a Gaussian counts as negligible (a
#: hundredth of a pixel's worth of colour per view: below an 8-bit step over the whole image)
TINY_WEIGHT = 1e-3


def gaussian_use(run_dir) -> dict:
    """The counts of one run (keys as printed by :func:`main`)."""
    from refgs import fast, runs
    from refgs.train.schedule import sh_degree_at
    from refgs.types import RenderConfig

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trainer = runs.load(run_dir).trainer
    g = trainer.gaussians()
    n = len(g)
    count, weight = np.zeros(n, np.int64), np.zeros(n)
    intersections = np.zeros(n, np.int64)
    config = RenderConfig(profile=trainer.cfg.profile,
                          sh_degree=sh_degree_at(trainer.t, trainer.cfg.sh_degree))
    for view in trainer.train_views:
        out = fast.render(g, view.camera, config)
        c, w = blended_fragments(out)
        count += c
        weight += w
        intersections += np.bincount(out.cache["lists"]["gauss"], minlength=n)
    unused = count == 0
    tiny = weight < TINY_WEIGHT * len(trainer.train_views)
    return {"run": str(run_dir), "t": trainer.t, "gaussians": n,
            "never_blended": int(unused.sum()), "tiny_weight": int(tiny.sum()),
            "intersections": int(intersections.sum()),
            "intersections_never_blended": int(intersections[unused].sum()),
            "intersections_tiny": int(intersections[tiny].sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run directories (their checkpoint.npz)")
    args = ap.parse_args()
    print("| run | t | Gaussians | never blended | total weight < 1e-3 / view "
          "| their share of the live intersections |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        r = gaussian_use(run)
        n, p = r["gaussians"], r["intersections"]
        print(f"| {r['run']} | {r['t']} | {n:,} | {r['never_blended']:,} "
              f"({r['never_blended'] / n:.1%}) | {r['tiny_weight']:,} ({r['tiny_weight'] / n:.1%}) "
              f"| {r['intersections_never_blended'] / p:.2%} / {r['intersections_tiny'] / p:.2%} |")


if __name__ == "__main__":
    main()
