"""Reference renderer benchmark: seconds, pixel-Gaussian pairs, pairs/s and peak memory.

    python benchmarks/bench_reference.py --n 10000 50000 --size 504x378 [--backward] [--repeats 3]

Pairs = sum over covered tiles of 256 x (tile list length): the pixel x Gaussian evaluations
the tile-based model performs.  Peak memory is the process's max RSS (resource.getrusage).
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import time

import numpy as np

import refgs
from refgs.synthetic import benchmark_scene


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--size", nargs="+", default=["504x378"])
    ap.add_argument("--backward", action="store_true", help="also time render_backward")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--profile", default="inria", choices=["inria", "gsplat"])
    args = ap.parse_args(argv)
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}, refgs {refgs.__version__}, dtype {args.dtype}, profile {args.profile}")
    print(f"{'N':>8} {'size':>9} {'fwd s':>7} {'bwd s':>7} {'pairs':>12} {'pairs/s fwd':>12} {'peak GB':>8}")
    for size in args.size:
        w, h = (int(x) for x in size.split("x"))
        for n in args.n:
            g, cam = benchmark_scene(n, w, h, seed=0, dtype=np.dtype(args.dtype))
            cfg = refgs.RenderConfig(profile=args.profile)
            tf, tb = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = refgs.render(g, cam, cfg)
                tf.append(time.perf_counter() - t0)
                if args.backward:
                    v = np.random.default_rng(1).normal(size=out.image.shape).astype(out.image.dtype)
                    t0 = time.perf_counter()
                    refgs.render_backward(out, v)
                    tb.append(time.perf_counter() - t0)
            pairs = 256 * int(out.cache["lists"]["gauss"].size)
            f = statistics.median(tf)
            b = statistics.median(tb) if tb else float("nan")
            print(f"{n:>8} {size:>9} {f:>7.2f} {b:>7.2f} {pairs:>12,d} {pairs / f:>12.3g} {peak_rss_gb():>8.2f}")


if __name__ == "__main__":
    main()
