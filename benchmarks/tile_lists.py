"""The tile lists of refgs.fast (live test, both counting-sort passes) and a whole render, timed
for one or more source trees side by side.

    python benchmarks/tile_lists.py [--source NAME=PATH ...] [--n 130000] [--size 504x378]
        [--threads 1 2] [--repeats 3]

Each source (a refgs checkout put first on PYTHONPATH; default: this one) runs in a fresh worker
process per repeat and thread count, the sources taking turns so that they share the machine's
load; a worker renders the benchmark scene (refgs.synthetic.benchmark_scene, float32, inria
profile) once, then times ``refgs.fast.render.build_tile_lists`` on that render's live
intersections and the whole ``refgs.fast.render``, best of BEST_OF calls each.  The table gives the
median over the repeats and a hash of the lists (gauss, offsets, pos): equal hashes mean the
sources build the same lists.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import statistics
import subprocess
import sys
import time

#: calls per timing, the fastest kept (the others saw the machine's other work)
BEST_OF = 9


def _best(fn, k: int = BEST_OF):
    times, result = [], None
    for _ in range(k):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e3, result


def worker(n: int, width: int, height: int, threads: int) -> dict:
    import numba
    import numpy as np
    from refgs import RenderConfig
    from refgs.synthetic import benchmark_scene
    fr = importlib.import_module("refgs.fast.render")

    numba.set_num_threads(threads)
    g, cam = benchmark_scene(n, width, height, seed=0)
    g = g.astype(np.float32)
    cfg = RenderConfig(profile="inria")
    out = fr.render(g, cam, cfg)
    rect = out.cache["tile_rect"]
    order = fr.depth_order(np.flatnonzero(out.visible), out.depths)
    eps = float(np.finfo(np.float32).eps)
    rect_off, live = fr.live_intersections(order, rect, out.cache["means2d_compositing"],
                                           out.conics, out.opacities, eps, True)
    gx, gy = -(-width // 16), -(-height // 16)
    t_build, lists = _best(lambda: fr.build_tile_lists(order, rect, gx, gy, rect_off, live))
    t_render, _ = _best(lambda: fr.render(g, cam, cfg))
    digest = hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in lists))
    return {"build_ms": t_build, "render_ms": t_render, "lists": digest.hexdigest()[:12],
            "intersections": int(lists[0].size)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", action="append", default=[], help="NAME=PATH of a refgs tree")
    ap.add_argument("--n", type=int, default=130_000, help="Gaussians")
    ap.add_argument("--size", default="504x378", help="image WxH")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    if args.worker:
        print(json.dumps(worker(args.n, width, height, args.threads[0])))
        return
    sources = [s.split("=", 1) for s in args.source] or [["this", "."]]
    runs: dict = {}
    for rep in range(args.repeats):
        for th in args.threads:
            for name, path in sources:
                env = dict(os.environ, PYTHONPATH=os.path.abspath(path))
                cmd = [sys.executable, __file__, "--worker", "--n", str(args.n), "--size",
                       args.size, "--threads", str(th)]
                res = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True,
                                                text=True).stdout.strip().splitlines()[-1])
                runs.setdefault((name, th), []).append(res)
                print(f"repeat {rep + 1}/{args.repeats}: {name}, {th} thread(s): "
                      f"lists {res['build_ms']:.2f} ms, render {res['render_ms']:.1f} ms",
                      file=sys.stderr, flush=True)
    first = sources[0][0]
    print(f"\n{args.n:,} Gaussians at {args.size}, medians of {args.repeats} repeats\n")
    print("| source | threads | tile lists (ms) | render (ms) | lists / first | render / first "
          "| lists hash |")
    print("|---|---|---|---|---|---|---|")
    for th in args.threads:
        base = runs[(first, th)]
        b_build = statistics.median(r["build_ms"] for r in base)
        b_render = statistics.median(r["render_ms"] for r in base)
        for name, _ in sources:
            rs = runs[(name, th)]
            build = statistics.median(r["build_ms"] for r in rs)
            render = statistics.median(r["render_ms"] for r in rs)
            hashes = sorted({r["lists"] for r in rs})
            print(f"| {name} | {th} | {build:.2f} | {render:.1f} | {build / b_build:.2f} "
                  f"| {render / b_render:.2f} | {', '.join(hashes)} |")


if __name__ == "__main__":
    main()
