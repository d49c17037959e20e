"""Where a training iteration's time goes, by phase, against what the machine allows.

    python benchmarks/train_profile.py RUN [RUN ...] [--source NAME=PATH[:DTYPE[:GEOMETRY]] ...]
        [--steps 10] [--warmup 2] [--repeats 3] [--threads 2] [--from T] [--method NAME]
        [--kernels] [--json OUT.json]

For each run directory (its ``checkpoint.npz``: a finished or an interrupted run; the directory is
only read), each ``--source`` (a refgs source tree put first on PYTHONPATH: e.g. ``new=.`` and
``old=/path/to/an/older/checkout``; default: this checkout) and each repeat, a fresh worker
process restores the trainer from the checkpoint, sets the iteration counter to ``--from``
(default: the checkpoint's, or ``iters - FINISHED_RUN_BACK`` for a finished run), runs
``--warmup`` iterations (compilation / cache loads) and then times ``--steps`` iterations phase by
phase.  The sources take turns within each repeat, so old and new code see the same load on the
machine; the table gives the median over the repeats of each phase, in ms per iteration, and the
ratio to the first source.  ``:DTYPE`` casts the parameters and Adam's moments (``float32``: what
``--dtype float32`` trains in); ``:GEOMETRY`` ``float64`` renders float32 Gaussians with
``refgs.fast.render(..., geometry="float64")`` (docs/fast.md, "Mixed precision").

Phases are timed by wrapping the functions that do them, exclusively (a phase's time excludes
the phases nested in it), so they add up to the iteration: projection (the per-Gaussian forward),
depth sort, tile lists (live test, counting sort), composite fwd, composite bwd, per-Gaussian bwd
(the per-Gaussian reduction and the backward of SH, projection and covariance), render / backward
glue (validation, allocation: what stays in Python), SSIM (the loss's SSIM and gradient; with a
backend's ``l1_ssim_loss`` the whole loss, L1 included), loss glue (L1, clamp), Adam, densify (statistics every iteration; densify-and-prune and the opacity
reset when they fall in the window), method hooks (e.g. FM's perturbation) and the trainer's own
glue.  ``--kernels`` adds a second table: the wall time of each compiled kernel of refgs.fast
(each call through parallel_for / parallel_bands, by kernel name), the finer view inside the
phases (e.g. the screen test ``tile_alive`` and the counting sort inside "tile lists").

Work and the machine's limit.  After the timed steps the first source's worker renders each
training view once and counts the pixel-Gaussian *pairs*: fragments the compositing blends
(power <= 0, alpha >= 1/255, before the pixel's stop); their mean over the views is the work of an
iteration.  The parent measures the machine in the same run, between the workers: a numpy float32
matrix product (``SGEMM_N`` squared, BLAS on every core) and a two-thread memory stream (copy,
``STREAM_BYTES``), best of ``LIMIT_REPEATS``.  The compute limit of an iteration is pairs x
``FLOPS_PER_PAIR`` / sgemm rate; the table gives each source's compositing time (forward +
backward) and iteration time as multiples of it, and pairs per second.  The last row, the share
of the iteration in the render stages (``RENDER_STAGES``), bounds what any work outside them can
save: a run whose other phases cost nothing would take that share of its time.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import warnings
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from fragments import blended_fragments        # benchmarks/fragments.py (run as a script)

#: floating-point operations per blended pair, forward + backward, counted from refgs.fast's
#: compositing lanes (refgs/fast/kernels.py): forward 9 (power) + 21 (exp: range reduction and a
#: degree-13 polynomial) + 13 (alpha, T test, 4 blends) = 43; backward 9 + 21 + 48 (alpha, T
#: recovery by a division, suffix, v_alpha, conic/mean gradient and 10 accumulations) = 78.
FLOPS_PER_PAIR = 121
#: a finished run is profiled from iteration iters - FINISHED_RUN_BACK: half-way between two of
#: FM's re-initialisations (every 1000 iterations, each followed by a 100-iteration frozen window
#: and an opacity reset), where an iteration costs what most of the run's do
FINISHED_RUN_BACK = 500
#: side of the float32 matrix product that measures the compute limit (2 n^3 flops)
SGEMM_N = 2048
#: bytes per array of the stream measurement (copy: read + write)
STREAM_BYTES = 256 * 2 ** 20
#: repeats of the machine measurements (best kept: the limit)
LIMIT_REPEATS = 3

#: kernel name (refgs.fast, run through parallel_for / parallel_bands) -> phase
KERNEL_PHASES = {
    "gaussians_forward": "projection",
    "tile_alive": "tile lists", "tile_counts": "tile lists", "tile_fill": "tile lists",
    "composite_forward": "composite fwd", "composite_backward": "composite bwd",
    "composite_forward_fma": "composite fwd", "composite_backward_fma": "composite bwd",
    "reduce_by_gaussian": "per-Gaussian bwd", "gaussians_backward": "per-Gaussian bwd",
    "_correlate_rows": "SSIM", "_correlate_cols": "SSIM", "_pointwise": "SSIM", "_combine": "SSIM",
    "_pass_moments": "SSIM", "_pass_adjoint": "SSIM", "_pass_planes": "SSIM",
    "_pass_loss_grad": "SSIM", "_pass_loss": "SSIM", "screen_inputs": "tile lists",
    "_update": "Adam",
}
PHASES = ("projection", "depth sort", "tile lists", "composite fwd", "composite bwd",
          "per-Gaussian bwd", "render glue", "backward glue", "SSIM", "loss glue", "Adam",
          "densify", "method hooks", "trainer glue", "other")
#: the compiled per-Gaussian and compositing stages of the render and its backward (the row
#: "share of the iteration in the render stages": what is left when every other phase -- loss,
#: Adam, densification, method hooks, glue -- costs nothing)
RENDER_STAGES = ("projection", "depth sort", "tile lists", "composite fwd", "composite bwd",
                 "per-Gaussian bwd")
#: hook names a method may have (the trainer calls them on ``trainer.method``)
METHOD_HOOKS = ("render_request", "param_gradients", "frozen_rows", "after_densify", "after_step",
                "before_render", "after_backward", "on_densify")


# --- the worker: one source, one repeat ---------------------------------------------------------
class Phases:
    """Exclusive wall time per phase: each wrapped call's time minus that of wrapped calls
    nested in it."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.calls = defaultdict(int)
        self._stack: list[float] = []
        self.on = False

    def wrap(self, fn, phase):
        """``fn`` timed as ``phase`` (a name, or a function of the call's arguments)."""
        def timed(*args, **kwargs):
            if not self.on:
                return fn(*args, **kwargs)
            name = phase(*args) if callable(phase) else phase
            self._stack.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                nested = self._stack.pop()
                self.seconds[name] += elapsed - nested
                self.calls[name] += 1
                if self._stack:
                    self._stack[-1] += elapsed
        return timed


def _kernel_phase(kernel, *_):
    name = getattr(kernel, "__name__", str(kernel))
    return KERNEL_PHASES.get(name, f"kernel {name}")


def _load_trainer(run_dir: Path):
    """The trainer of a run directory, restored from its checkpoint (the run-directory API of the
    refgs on the path: refgs.runs where it exists, else the CLI of older trees)."""
    import importlib
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            runs = importlib.import_module("refgs.runs")
        except ImportError:
            runs = None
        if runs is not None and hasattr(runs, "load"):
            return runs.load(run_dir).trainer
        return getattr(importlib.import_module("refgs.cli"), "_restore")(run_dir)[-1]


class KernelTimes:
    """Wall time per compiled kernel (the per-kernel rows of ``--kernels``): ``wrap`` a runner
    (refgs.fast.render.parallel_for / parallel_bands); a call nested in another wrapped call
    (parallel_bands runs parallel_for) is counted once, by the outer one."""

    def __init__(self, phases: Phases):
        self.phases = phases
        self.seconds: dict = {}
        self._depth = 0

    def wrap(self, run):
        def timed(kernel, *args, **kwargs):
            if not self.phases.on or self._depth:
                return run(kernel, *args, **kwargs)
            self._depth += 1
            t0 = time.perf_counter()
            try:
                return run(kernel, *args, **kwargs)
            finally:
                self._depth -= 1
                name = getattr(kernel, "__name__", str(kernel))
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
        return timed


def _instrument(trainer, phases: Phases, kernels: KernelTimes) -> None:
    import importlib
    fr = importlib.import_module("refgs.fast.render")     # the module (refgs.fast.render is
    tr = importlib.import_module("refgs.train.trainer")   # also the name of a function)

    kernel_runner = phases.wrap(kernels.wrap(fr.parallel_for), _kernel_phase)
    fr.parallel_for = kernel_runner
    fr.parallel_bands = phases.wrap(kernels.wrap(fr.parallel_bands), _kernel_phase)
    for name in ("refgs.fast.ssim", "refgs.fast.adam"):    # their own reference to parallel_for
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        if getattr(mod, "parallel_for", None) is not None:
            mod.parallel_for = phases.wrap(kernels.wrap(mod.parallel_for), _kernel_phase)
    fr.depth_order = phases.wrap(fr.depth_order, "depth sort")
    for name in ("live_intersections", "build_tile_lists"):
        if hasattr(fr, name):
            setattr(fr, name, phases.wrap(getattr(fr, name), "tile lists"))
    b = trainer.backend
    b.render = phases.wrap(b.render, "render glue")
    b.render_backward = phases.wrap(b.render_backward, "backward glue")
    for helper in ("ssim_and_grad", "l1_ssim_loss"):     # the loss's compiled chain (TRN-08)
        if getattr(b, helper, None) is not None:
            setattr(b, helper, phases.wrap(getattr(b, helper), "SSIM"))
    for mod in (tr,):
        if hasattr(mod, "photometric_loss"):
            mod.photometric_loss = phases.wrap(mod.photometric_loss, "loss glue")
        for name in ("densify_and_prune", "reset_opacity"):
            if hasattr(mod, name):
                setattr(mod, name, phases.wrap(getattr(mod, name), "densify"))
    trainer.stats.accumulate = phases.wrap(trainer.stats.accumulate, "densify")
    trainer.adam.step = phases.wrap(trainer.adam.step, "Adam")
    for hook in METHOD_HOOKS:
        if hasattr(trainer.method, hook):
            timed = phases.wrap(getattr(trainer.method, hook), "method hooks")
            setattr(trainer.method, hook, timed)
    trainer.step = phases.wrap(trainer.step, "trainer glue")


def count_pairs(out) -> tuple[int, int]:
    """(blended fragments, candidate lane pairs) of a refgs.fast render: the pixel-Gaussian pairs
    the compositing blends (counted per pixel over its live tile list up to its last blended
    slot, in float64), and the (pixel, slot) pairs the screen hands to the forward's lanes (row
    lists or half-row masks; an upper bound: a row stops once its pixels have; 0 if the render
    keeps neither)."""
    from refgs.constants import TILE_SIZE
    c = out.cache
    n = int(blended_fragments(out)[0].sum())
    if "row_mask" in c:                     # per intersection, the half rows its screen kept
        m = c["row_mask"].astype(np.int64)
        half = TILE_SIZE // 2
        lanes = int(sum(int(np.count_nonzero((m >> b) & 1)) for b in range(2 * TILE_SIZE))) * half
    elif "rows" in c:                       # per tile and row, the number of slots
        lanes = int(np.sum(c["rows"][0])) * TILE_SIZE
    else:
        lanes = 0
    return int(n), lanes


def worker(args) -> dict:
    from refgs import fast
    from refgs.types import RenderConfig

    trainer = _load_trainer(args.run)
    if args.method:
        try:                                    # refgs.methods' one table (this checkout)
            from refgs.methods import make_method
        except ImportError:                     # an older source tree: the trainer's registry
            from refgs.train.trainer import get_method as make_method
        trainer.method = make_method(args.method, {})
        trainer.method.setup(trainer)
    if args.dtype:
        dt = np.dtype(args.dtype)
        for store in (trainer.params, trainer.adam.m, trainer.adam.v):
            for k in store:
                store[k] = store[k].astype(dt)
    if args.dtype or args.geometry:
        # refgs.fast in the Gaussians' own dtype (a registry backend would cast them to the run's)
        geometry = args.geometry or "input"
        trainer.backend.render = lambda g, cam, cfg: fast.render(g, cam, cfg, geometry=geometry)
        trainer.backend.render_backward = fast.render_backward
    start = args.start if args.start is not None else (
        trainer.t if trainer.t + args.warmup + args.steps <= trainer.cfg.iters
        else trainer.cfg.iters - FINISHED_RUN_BACK)
    trainer.t = start
    phases = Phases()
    kernels = KernelTimes(phases)
    _instrument(trainer, phases, kernels)
    for _ in range(args.warmup):
        trainer.step()
    n0 = trainer.n
    phases.on = True
    t0 = time.perf_counter()
    for _ in range(args.steps):
        trainer.step()
    wall = time.perf_counter() - t0
    phases.on = False
    res = {"ms": {k: 1e3 * v / args.steps for k, v in phases.seconds.items()},
           "kernel_ms": {k: 1e3 * v / args.steps for k, v in kernels.seconds.items()},
           "wall_ms": 1e3 * wall / args.steps, "n_gaussians": [n0, trainer.n],
           "t": [start + args.warmup + 1, trainer.t], "dtype": str(trainer.params["means"].dtype),
           "geometry": args.geometry or "input"}
    if args.pairs:
        import refgs.train.schedule as sch
        counts = []
        for v in trainer.train_views:
            rcfg = RenderConfig(profile=trainer.cfg.profile,
                                sh_degree=sch.sh_degree_at(trainer.t, trainer.cfg.sh_degree))
            out = fast.render(trainer.gaussians(), v.camera, rcfg)
            counts.append(count_pairs(out))
        res["pairs"] = float(np.mean([c[0] for c in counts]))
        res["lane_pairs"] = float(np.mean([c[1] for c in counts]))
    return res


# --- the machine --------------------------------------------------------------------------------
def machine_limits() -> dict:
    """Best-of-LIMIT_REPEATS float32 matrix-product rate (flop/s, numpy's BLAS on every core) and
    two-thread copy bandwidth (bytes/s, read + write)."""
    from numba import njit

    @njit(nogil=True, cache=False)
    def copy(a, b, lo, hi):
        for i in range(lo, hi):
            b[i] = a[i]

    rng = np.random.default_rng(0)
    x = rng.standard_normal((SGEMM_N, SGEMM_N)).astype(np.float32)
    y = rng.standard_normal((SGEMM_N, SGEMM_N)).astype(np.float32)
    a = np.ones(STREAM_BYTES // 4, np.float32)
    b = np.zeros_like(a)
    half = a.size // 2
    copy(a[:16], b[:16], 0, 16)
    gemm, stream = [], []
    with ThreadPoolExecutor(2) as ex:
        for _ in range(LIMIT_REPEATS):
            t0 = time.perf_counter()
            x @ y
            gemm.append(2.0 * SGEMM_N ** 3 / (time.perf_counter() - t0))
            t0 = time.perf_counter()
            list(ex.map(lambda r: copy(a, b, *r), [(0, half), (half, a.size)]))
            stream.append(2.0 * a.nbytes / (time.perf_counter() - t0))
    return {"sgemm_flops": max(gemm), "stream_bytes": max(stream)}


# --- the parent ---------------------------------------------------------------------------------
def _parse_source(text: str) -> dict:
    name, _, rest = text.partition("=")
    if not rest:
        raise SystemExit(f"--source: expected NAME=PATH[:DTYPE[:GEOMETRY]], got {text!r}")
    path, dtype, geometry = (rest.split(":") + [None, None])[:3]
    if not Path(path, "refgs").is_dir():
        raise SystemExit(f"--source {text}: {path}/refgs is not a refgs source tree")
    if (dtype not in (None, "", "float32", "float64")
            or geometry not in (None, "", "input", "float64")):
        raise SystemExit(f"--source {text}: DTYPE float32|float64, GEOMETRY input|float64")
    return {"name": name, "path": str(Path(path).absolute()), "dtype": dtype or None,
            "geometry": geometry or None}


def run_worker(src: dict, run: Path, args, pairs: bool) -> dict:
    cmd = [sys.executable, str(Path(__file__).absolute()), "--worker", str(run),
           "--steps", str(args.steps), "--warmup", str(args.warmup)]
    for flag, value in (("--from", args.start), ("--method", args.method),
                        ("--dtype", src["dtype"]), ("--geometry", src["geometry"])):
        if value is not None:
            cmd += [flag, str(value)]
    if pairs:
        cmd.append("--pairs")
    env = dict(os.environ, PYTHONPATH=src["path"], NUMBA_NUM_THREADS=str(args.threads),
               OMP_NUM_THREADS=str(args.threads), OPENBLAS_NUM_THREADS=str(args.threads))
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=src["path"])
    if p.returncode != 0:
        raise SystemExit(f"worker {src['name']} on {run} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def _row(cells: list) -> str:
    return "| " + " | ".join(cells) + " |"


def table(run: Path, sources: list, results: dict, limits: list, pairs: float,
          lanes: dict, kernels: bool = False) -> str:
    """The markdown table of one run: medians over the repeats, ratios to the first source
    (with ``kernels``, then one row per compiled kernel that ran through parallel_for)."""
    sgemm = statistics.median(l["sgemm_flops"] for l in limits)
    stream = statistics.median(l["stream_bytes"] for l in limits)
    t_lim = pairs * FLOPS_PER_PAIR / sgemm
    names = [s["name"] for s in sources]

    def ms(r, ph):              # phases this table does not name are "other"
        if ph != "other":
            return r["ms"].get(ph, 0.0)
        return sum(v for k, v in r["ms"].items() if k not in PHASES)
    med = {n: {ph: statistics.median(ms(r, ph) for r in results[n]) for ph in PHASES}
           for n in names}
    wall = {n: statistics.median(r["wall_ms"] for r in results[n]) for n in names}
    first = names[0]
    r0 = results[first][0]
    lines = [f"### {run.name}: t = {r0['t'][0]}..{r0['t'][1]}, {r0['n_gaussians'][0]:,} Gaussians",
             "",
             f"pairs (blended pixel-Gaussian fragments) per iteration: {pairs / 1e6:.2f} M; "
             f"machine in this run: sgemm {sgemm / 1e9:.0f} GFLOP/s, stream {stream / 1e9:.1f} "
             f"GB/s; compute limit of an iteration ({FLOPS_PER_PAIR} flop/pair): "
             f"{1e3 * t_lim:.1f} ms",
             "",
             _row(["phase (ms / iteration)"] + [
                 f"{n} ({results[n][0]['dtype']}"
                 f"{', geom64' if results[n][0]['geometry'] == 'float64' else ''})" for n in names]
                 + [f"{n} / {first}" for n in names[1:]]),
             "|---" * (2 * len(names)) + "|"]
    for ph in PHASES + ("total",):
        vals = {n: (sum(med[n].values()) if ph == "total" else med[n][ph]) for n in names}
        ratios = [f"{vals[n] / vals[first]:.2f}" if vals[first] > 0 else "-" for n in names[1:]]
        lines.append(_row([ph] + [f"{vals[n]:.1f}" for n in names] + ratios))
    comp = {n: med[n]["composite fwd"] + med[n]["composite bwd"] for n in names}
    rows = [("wall per iteration (ms)", {n: f"{wall[n]:.1f}" for n in names}),
            ("lanes evaluated per pair (forward)",
             {n: f"{lanes[n] / pairs:.2f}" if lanes.get(n) else "-" for n in names}),
            ("pairs / s, compositing (M)", {n: f"{pairs / comp[n] / 1e3:.0f}" for n in names}),
            ("pairs / s, iteration (M)", {n: f"{pairs / wall[n] / 1e3:.0f}" for n in names}),
            ("compositing / compute limit", {n: f"{comp[n] / 1e3 / t_lim:.1f}x" for n in names}),
            ("iteration / compute limit", {n: f"{wall[n] / 1e3 / t_lim:.1f}x" for n in names}),
            ("share of the iteration in the render stages",
             {n: f"{sum(med[n][ph] for ph in RENDER_STAGES) / sum(med[n].values()):.0%}"
              for n in names})]
    for label, vals in rows:
        lines.append(_row([label] + [vals[n] for n in names] + [""] * (len(names) - 1)))
    if kernels:
        lines += ["", _row(["compiled kernel (ms / iteration, inside the phases above)"] + names
                           + [f"{n} / {first}" for n in names[1:]]),
                  "|---" * (2 * len(names)) + "|"]
        kmed = {n: {} for n in names}
        for n in names:
            for k in {k for r in results[n] for k in r.get("kernel_ms", {})}:
                kmed[n][k] = statistics.median(r.get("kernel_ms", {}).get(k, 0.0)
                                               for r in results[n])
        order = sorted({k for n in names for k in kmed[n]},
                       key=lambda k: -max(kmed[n].get(k, 0.0) for n in names))
        for k in order:
            vals = {n: kmed[n].get(k, 0.0) for n in names}
            ratios = [f"{vals[n] / vals[first]:.2f}" if vals[first] > 0 else "-"
                      for n in names[1:]]
            lines.append(_row([f"`{k}`"] + [f"{vals[n]:.1f}" for n in names] + ratios))
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="run directories (their checkpoint.npz)")
    ap.add_argument("--source", action="append", default=[],
                    help="NAME=PATH[:DTYPE[:GEOMETRY]], a refgs checkout to time (repeatable; "
                         "default: this one); the first is the ratios' base")
    ap.add_argument("--steps", type=int, default=10, help="timed iterations per worker")
    ap.add_argument("--warmup", type=int, default=2, help="untimed iterations first")
    ap.add_argument("--repeats", type=int, default=3, help="workers per source and run")
    ap.add_argument("--threads", type=int, default=2, help="NUMBA_NUM_THREADS of the workers")
    ap.add_argument("--from", dest="start", type=int, default=None,
                    help="iteration to start from (default: the checkpoint's, or iters - 500)")
    ap.add_argument("--method", default=None, help="profile this method instead of the run's")
    ap.add_argument("--json", type=Path, default=None, help="write every measurement here")
    ap.add_argument("--kernels", action="store_true",
                    help="add a row per compiled kernel (refgs.fast's parallel_for calls)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--pairs", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--dtype", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--geometry", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        args.run = args.runs[0].absolute()
        print(json.dumps(worker(args)))
        return
    for run in args.runs:
        if not (run / "checkpoint.npz").is_file():
            raise SystemExit(f"{run}: no checkpoint.npz (expected a run directory)")
    sources = [_parse_source(s) for s in args.source] or [
        _parse_source(f"this={Path(__file__).absolute().parents[1]}")]
    report = {"sources": sources, "runs": {}}
    for run in args.runs:
        run = run.absolute()
        results = {s["name"]: [] for s in sources}
        limits, pairs, lanes = [], 0.0, {}
        for r in range(args.repeats):
            limits.append(machine_limits())
            for s in sources:
                res = run_worker(s, run, args, pairs=(r == 0))
                results[s["name"]].append(res)
                if "pairs" in res:
                    lanes[s["name"]] = res["lane_pairs"]
                    if s is sources[0]:
                        pairs = res["pairs"]
                print(f"# {run.name} repeat {r + 1}/{args.repeats} {s['name']}: "
                      f"{res['wall_ms']:.1f} ms/it", file=sys.stderr, flush=True)
        print(table(run, sources, results, limits, pairs, lanes, args.kernels) + "\n",
              flush=True)
        report["runs"][str(run)] = {"results": results, "limits": limits, "pairs": pairs,
                                    "lane_pairs": lanes}
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
