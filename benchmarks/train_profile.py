"""Where one training iteration's time goes, at a run's size (docs/performance.md, "Training").

    NUMBA_NUM_THREADS=1 python benchmarks/train_profile.py RUN_DIR [--method fm] [--from 9000]
                                [--steps 30] [--top 25] [--dtype float32] [--geometry float64]

Loads the run's checkpoint (refgs train's own restore; the run directory is not changed), sets the
iteration counter to ``--from`` (by default past densification, so the Gaussian count stays the
checkpoint's), optionally swaps the method (``--method fm`` profiles the flat-minima method on the
Gaussians of, say, a DropGaussian run), runs two warm-up iterations (compilation), then profiles
``--steps`` iterations with cProfile and prints the functions by own time and by cumulative time,
as seconds per iteration.  Numba kernels appear as single calls (their time is their own).
``--dtype float32`` casts the parameters and Adam's moments (what ``refgs train --dtype float32``
trains in); ``--geometry float64`` renders with ``refgs.fast.render(..., geometry="float64")``
(float32 compositing of a float64 per-Gaussian stage; fast backend, float32 only).
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import time
import warnings
from pathlib import Path

import numba
import numpy as np

from refgs.cli import _restore
from refgs.train.trainer import get_method


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--method", default=None, help="profile this method instead of the run's")
    ap.add_argument("--from", dest="start", type=int, default=9000)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--dtype", choices=("float32", "float64"), default=None)
    ap.add_argument("--geometry", choices=("input", "float64"), default="input")
    args = ap.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, cfg, trainer = _restore(args.run.absolute())
    if args.method:
        trainer.method = get_method(args.method, {})
        trainer.method.setup(trainer)
    if args.dtype:
        dt = np.dtype(args.dtype)
        for store in (trainer.params, trainer.adam.m, trainer.adam.v):
            for k in store:
                store[k] = store[k].astype(dt)
    if args.geometry != "input":
        from refgs import fast
        trainer.backend.render = lambda g, cam, cfg: fast.render(g, cam, cfg, geometry=args.geometry)
    trainer.t = args.start
    for _ in range(2):
        trainer.step()
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    for _ in range(args.steps):
        trainer.step()
    prof.disable()
    wall = (time.perf_counter() - t0) / args.steps
    print(f"{args.run}: method {trainer.method.name}, "
          f"{trainer.n} Gaussians, {trainer.params['means'].dtype}, geometry {args.geometry}, "
          f"t = {args.start}..{trainer.t}, {numba.get_num_threads()} thread(s): "
          f"{wall:.3f} s per iteration (wall, profiled)")
    stats = pstats.Stats(prof)
    for key in ("tottime", "cumulative"):
        print(f"\n--- by {key}, seconds per iteration ---")
        rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2 if key == "tottime" else 3],
                      reverse=True)[:args.top]
        for (file, line, name), (_, ncalls, tt, ct, _) in rows:
            where = f"{Path(file).parent.name}/{Path(file).name}:{line}" if line else file
            print(f"{tt / args.steps:8.4f} {ct / args.steps:8.4f} {ncalls / args.steps:7.1f}  {name}  ({where})")


if __name__ == "__main__":
    main()
