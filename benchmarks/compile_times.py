"""refgs.fast compile and cache-load times (docs/fast.md, "Compilation").

    NUMBA_CACHE_DIR=$(mktemp -d) python benchmarks/compile_times.py    # empty cache: compiles
    NUMBA_CACHE_DIR=<same dir> python benchmarks/compile_times.py      # warm cache: loads

Times ``import refgs.fast``, then in each dtype the first ``render`` and ``render_backward`` of
the seeded 2000-Gaussian benchmark scene at 128x96 (compilation, or loading from the cache) and a
second call of each (the steady state).
"""
from __future__ import annotations

import os
import platform
import time

t0 = time.perf_counter()
import numpy as np  # noqa: E402

import refgs.fast as fast  # noqa: E402
from refgs.synthetic import benchmark_scene  # noqa: E402

IMPORT_S = time.perf_counter() - t0
#: the scene: small enough that the steady-state calls take milliseconds
N, WIDTH, HEIGHT, SEED = 2000, 128, 96, 0


def main() -> None:
    import numba
    g, cam = benchmark_scene(N, WIDTH, HEIGHT, seed=SEED)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, numba "
          f"{numba.__version__}, {numba.get_num_threads()} threads, NUMBA_CACHE_DIR="
          f"{os.environ.get('NUMBA_CACHE_DIR', '(default: refgs/fast/__pycache__)')}")
    print(f"import refgs.fast: {IMPORT_S:.2f} s")
    for dt in (np.float64, np.float32):
        gg, v = g.astype(dt), np.ones((HEIGHT, WIDTH, 3), dt)
        t0 = time.perf_counter()
        out = fast.render(gg, cam)
        t1 = time.perf_counter()
        fast.render_backward(out, v)
        t2 = time.perf_counter()
        out = fast.render(gg, cam)
        t3 = time.perf_counter()
        fast.render_backward(out, v)
        t4 = time.perf_counter()
        print(f"{np.dtype(dt).name}: first render {t1 - t0:.2f} s, first backward {t2 - t1:.2f} s; "
              f"later {1e3 * (t3 - t2):.1f} ms / {1e3 * (t4 - t3):.1f} ms")


if __name__ == "__main__":
    main()
