"""``refgs bench``: speed against error for every available backend (docs/performance.md).

    refgs bench [--n 1000 10000 50000 200000] [--size 128x128 504x378 1008x756]
                [--backends ref64 ref32 fast64 fast32 fast32g torch64 torch32 gsplat]
                [--fern-run RUN_DIR] [--repeats 3] [--profile inria] [--out DIR]

Backends are resolved by the registry (refgs.backends): its names, or ``module:object`` for any
other renderer with the backend protocol and a ``dtype``; one that cannot run here (a missing
optional dependency, no CUDA device, another profile) is listed as n/a with the reason.

For each scene (the seeded synthetic scene of ``refgs.synthetic.benchmark_scene`` at every N and
image size, and optionally fern ``images_8`` with the Gaussians of a saved fern run) every
available backend renders and differentiates the same float32-representable inputs (the scene
is rounded to float32 once, so float32 backends see exactly what float64 ones see).  Timing:
the first call of each backend (numba compilation or on-disk cache load, torch warm-up) is
reported separately; then ``--repeats`` rounds each time every backend in turn (interleaved, so a
changing load hits all alike); medians of ``time.perf_counter``.

Error, against the float64 reference ``refgs.render``/``refgs.render_backward`` on the same
inputs (where the reference is not run -- larger than :data:`LIMITS` -- against ``refgs.fast`` at
float64, which the oracle certifies equal to the reference to 1e-12; the table says which):

* image: max |difference| over pixels; for float32 backends outside the near-tie pixels that
  ``refgs.fast.ties.find_ties`` flags on the float64 render (alpha at 1/255, the T stop, depth
  order, geometry), whose count is reported beside it -- never hidden by a looser tolerance; the
  bands are the backend's (``BenchBackend.bands``): ``fast32g`` (refgs.fast float32 with
  ``geometry="float64"``) decides geometry and depth order in float64, so only the per-pixel
  bands apply to it (refgs.fast.ties.GEOMETRY64_BANDS);
* gradients: for L = <v, image> with a seeded normal cotangent v (zeroed on backward near-ties
  for float32 backends, and the kink-tied Gaussians' rows left out), the worst field's relative
  L2 error and the worst element, |got - ref| / max|ref| of its field;
* for float32 backends also the same without any exclusion (``image_max_abs_all`` over every
  pixel, ``grad_rel_l2_unmasked`` for the unmasked v): where these meet the bounds, no pixel
  needed excluding (the targets' ``no_exclusion_needed``).

Writes ``bench.json``, ``bench.csv``, ``pareto.png`` (time against error) and ``scaling.png``
(time against pixel-Gaussian pairs, with the fitted growth exponent per backend) into ``--out``.
"""
from __future__ import annotations

import csv
import io
import json
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..backends import BackendUnavailable, get_backend
from ..errors import ConfigError
from ..io.atomic import atomic_write_json, atomic_write_text
from ..synthetic import benchmark_scene
from ..train.checkpoint import cpu_name, float_environment, peak_rss_gb
from ..types import RenderConfig

DEFAULT_NS = (1_000, 10_000, 50_000, 200_000)
DEFAULT_SIZES = ("128x128", "504x378", "1008x756")
#: The largest scene (Gaussians, pixels) a slow backend is timed on: the numpy reference up to
#: 50k at 504x378 (beyond that one render takes minutes), the torch transcription up to
#: 10k at 504x378 (18 s per forward + backward there on the 2-core machine; it is a correctness
#: cross-check written for clarity, not speed).
LIMITS = {"ref64": (50_000, 504 * 378), "ref32": (50_000, 504 * 378),
          "torch64": (10_000, 504 * 378), "torch32": (10_000, 504 * 378)}
#: seed of the cotangent v of L = <v, image>
COTANGENT_SEED = 1
#: seed of the synthetic scenes (refgs.synthetic.benchmark_scene)
SCENE_SEED = 0
#: the targets of docs/performance.md ("Targets"), checked and printed for the 50k / 504x378 scene
TARGET_SCENE = (50_000, "504x378")
TARGET_SPEEDUP = 30.0
TARGET_IMAGE_ERR = 1e-5
TARGET_TIE_FRACTION = 1e-4
TARGET_GRAD_REL_L2 = 1e-4
GRAD_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d")


@dataclass
class BenchBackend:
    name: str
    label: str
    dtype: str
    render: Callable
    backward: Callable
    #: which near-tie bands apply to a float32 backend (a key of TIE_BANDS): "float32" for
    #: float32 throughout, "float32-compositing" for float32 compositing of float64 geometry
    bands: str = "float32"


def bench_backend(name: str, profile: str) -> BenchBackend:
    """The backend ``name`` of ``--backends`` (a name of refgs.backends or module:object) at
    ``profile``; BackendUnavailable naming the missing piece when it cannot run here."""
    be = get_backend(name, profile, flag="--backends")
    if be.dtype not in ("float32", "float64"):
        raise ConfigError(f"--backends {name}: declares no dtype (expected a 'dtype' attribute, "
                          f"float32 or float64, got {be.dtype!r})")
    return BenchBackend(name, be.label, be.dtype, be.render, be.render_backward, be.bands)


#: Every backend of the registry the bench times by default (each renders one dtype).
ALL_BACKENDS = ("ref64", "ref32", "fast64", "fast32", "fast32g", "torch64", "torch32", "gsplat")


def _parse_size(s: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in s.lower().split("x"))
        if w < 1 or h < 1:
            raise ValueError
        return w, h
    except ValueError:
        raise ConfigError(f"--size: expected WIDTHxHEIGHT with positive integers, got {s!r}") from None


def synthetic_scenes(ns, sizes):
    """(label, n, size, gaussians float64 with float32-representable values, camera)."""
    for size in sizes:
        w, h = _parse_size(size)
        for n in ns:
            g, cam = benchmark_scene(n, w, h, seed=SCENE_SEED)
            yield f"synthetic N={n} {w}x{h}", n, f"{w}x{h}", g.astype(np.float32).astype(np.float64), cam


def fern_scene(run_dir: str | Path):
    """A saved run's Gaussians (its checkpoint's exact parameters, as ``refgs eval`` uses them;
    the run may be unfinished) seen from its first test view."""
    from ..runs import load
    from ..types import Gaussians
    _, cfg, trainer = load(run_dir)
    g = Gaussians(**{k: np.asarray(v, np.float64) for k, v in trainer.params.items()})
    view = trainer.test_views[0]
    cam = view.camera
    size = f"{cam.width}x{cam.height}"
    return (f"{Path(cfg.scene).name} {cfg.views}-view {cfg.method} run at iteration {trainer.t} "
            f"({view.name})", len(g), size, g.astype(np.float32).astype(np.float64), cam)


def _within(name: str, n: int, size: str) -> bool:
    if name not in LIMITS:
        return True
    w, h = _parse_size(size)
    return n <= LIMITS[name][0] and w * h <= LIMITS[name][1]


def _timed(fn, *args):
    t = time.perf_counter()
    r = fn(*args)
    return r, time.perf_counter() - t


def _grad_errors(got, ref, rows=None) -> dict:
    worst_l2, worst_field, worst_el = 0.0, None, 0.0
    for f in GRAD_FIELDS:
        a = np.asarray(getattr(got, f), np.float64)
        b = np.asarray(getattr(ref, f), np.float64)
        if rows is not None:
            a, b = a[rows], b[rows]
        nb, mb = np.linalg.norm(b), np.max(np.abs(b), initial=0.0)
        l2 = float(np.linalg.norm(a - b) / nb) if nb > 0 else float(np.linalg.norm(a))
        el = float(np.max(np.abs(a - b), initial=0.0) / mb) if mb > 0 else float(np.max(np.abs(a), initial=0.0))
        if l2 >= worst_l2:
            worst_l2, worst_field = l2, f
        worst_el = max(worst_el, el)
    return {"grad_rel_l2": worst_l2, "grad_worst_field": worst_field, "grad_worst_element": worst_el}


def tie_bands(key: str):
    """The refgs.fast.ties bands of a BenchBackend.bands key."""
    from ..fast.ties import FLOAT32_BANDS, GEOMETRY64_BANDS
    return {"float32": FLOAT32_BANDS, "float32-compositing": GEOMETRY64_BANDS}[key]


def _fast64_render(g64, cam, cfg):
    """A float64 refgs.fast render for the tie flags, or None without numba."""
    try:
        be = get_backend("fast64", cfg.profile, flag="--backends")
    except BackendUnavailable:
        return None
    return be.render(g64, cam, cfg)


def bench_scene(label, n, size, g64, cam, backends, repeats: int, profile: str) -> dict:
    """Time and compare every backend on one scene (module docstring)."""
    cfg = RenderConfig(profile=profile)
    w, h = _parse_size(size)
    v = np.random.default_rng(COTANGENT_SEED).normal(size=(h, w, 3))
    inputs = {"float64": g64, "float32": g64.astype(np.float32)}
    active = [b for b in backends if _within(b.name, n, size)]
    res = {"scene": label, "n": int(n), "size": size, "profile": profile, "backends": {},
           "skipped": sorted(b.name for b in backends if b not in active)}
    first = {}
    for b in active:
        out, tf = _timed(b.render, inputs[b.dtype], cam, cfg)
        _, tb = _timed(b.backward, out, v.astype(b.dtype))
        first[b.name] = {"forward_s": tf, "backward_s": tb}
    times = {b.name: {"fwd": [], "bwd": []} for b in active}
    outs = {}
    for _ in range(repeats):
        for b in active:
            out, tf = _timed(b.render, inputs[b.dtype], cam, cfg)
            grads, tb = _timed(b.backward, out, v.astype(b.dtype))
            times[b.name]["fwd"].append(tf)
            times[b.name]["bwd"].append(tb)
            outs[b.name] = (out, grads)
    ref_name = "ref64" if "ref64" in outs else ("fast64" if "fast64" in outs else None)
    res["error_reference"] = ref_name
    ties = {}                                  # bands key -> find_ties result
    keys = sorted({b.bands for b in active if b.dtype == "float32"})
    if keys:
        # the near-tie flags come from a float64 refgs.fast render (its cache holds what
        # find_ties reads); made here, untimed, when fast64 is not among the backends
        tie_src = outs["fast64"][0] if "fast64" in outs else _fast64_render(g64, cam, cfg)
        if tie_src is not None:
            from ..fast.ties import find_ties
            ties = {k: find_ties(tie_src, tie_bands(k)) for k in keys}
    if "fast64" in outs:
        res["pixel_gaussian_pairs"] = 256 * int(outs["fast64"][0].cache["lists"]["full_size"])
    elif "ref64" in outs:
        res["pixel_gaussian_pairs"] = 256 * int(outs["ref64"][0].cache["lists"]["gauss"].size)
    refs = {}
    if ref_name is not None:
        ref_out, ref_g = outs[ref_name]
        ref_be = next(b for b in active if b.name == ref_name)
        refs["float64"] = (ref_out, ref_g, None)
        for k, tk in ties.items():
            v_masked = np.where(tk["backward"][..., None], 0.0, v)
            refs[k] = (ref_out, ref_be.backward(ref_out, v_masked), ~tk["kink_gaussians"])
    for b in active:
        t = times[b.name]
        fwd, bwd = statistics.median(t["fwd"]), statistics.median(t["bwd"])
        row = {"label": b.label, "dtype": b.dtype, "forward_s": fwd, "backward_s": bwd,
               "forward_backward_s": statistics.median(np.add(t["fwd"], t["bwd"])),
               "first_call": first[b.name], "all_s": t}
        if ref_name is not None and b.name != ref_name:
            tk = ties.get(b.bands) if b.dtype == "float32" else None
            ref_out, ref_g, rows = refs[b.bands] if tk is not None else refs["float64"]
            out, grads = outs[b.name]
            err = np.max(np.abs(np.asarray(out.image, np.float64) - ref_out.image), axis=-1)
            if tk is not None:
                row["tie_bands"] = b.bands
                # without any exclusion: every pixel, and the gradients of the unmasked cotangent
                row["image_max_abs_all"] = float(err.max())
                row["grad_rel_l2_unmasked"] = _grad_errors(grads, refs["float64"][1])["grad_rel_l2"]
                mask = tk["forward"]
                row["tie_pixels"] = int(mask.sum())
                row["image_max_abs"] = float(np.max(np.where(mask, 0.0, err), initial=0.0))
                row["image_max_abs_at_ties"] = float(np.max(np.where(mask, err, 0.0), initial=0.0))
                row["tie_pixels_differing"] = int(np.sum(mask & (err > TARGET_IMAGE_ERR)))
                grads = b.backward(out, np.where(tk["backward"][..., None], 0.0, v).astype(b.dtype))
            else:
                # float64, or float32 without numba: no flags (None = not known, not "none")
                row["tie_pixels"] = 0 if b.dtype == "float64" else None
                row["image_max_abs"] = float(err.max())
            row.update(_grad_errors(grads, ref_g, rows))
        res["backends"][b.name] = row
    if "ref64" in res["backends"]:
        base = res["backends"]["ref64"]["forward_backward_s"]
        for row in res["backends"].values():
            row["speedup_vs_ref64"] = base / row["forward_backward_s"]
    res["peak_rss_gb"] = peak_rss_gb()
    return res


def machine_info() -> dict:
    info = {"machine": platform.machine(), "cpu": cpu_name(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__,
            "float_environment": float_environment(), "loadavg_before": list(os.getloadavg())}
    try:
        import numba
        info["numba"], info["numba_threads"] = numba.__version__, numba.get_num_threads()
    except ImportError:
        info["numba"] = None
    try:
        import torch
        info["torch"], info["torch_threads"] = torch.__version__, torch.get_num_threads()
    except ImportError:
        info["torch"] = None
    from .. import __version__
    info["refgs"] = __version__
    return info


def _fmt(x, spec=".2e"):
    return "-" if x is None else format(x, spec)


def _ties(b: dict) -> str:
    if "tie_pixels" not in b:
        return "-"
    return "n/a (no numba)" if b["tie_pixels"] is None else str(b["tie_pixels"])


def table(results: list[dict]) -> str:
    """The results as one Markdown table (printed and written to docs)."""
    lines = ["| scene | backend | first call s | fwd s | bwd s | fwd+bwd s | x ref64 | image err | ties "
             "(> 1e-5) | image err, all px | grad rel L2 | grad worst el. | vs |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for name, b in r["backends"].items():
            fc = b["first_call"]["forward_s"] + b["first_call"]["backward_s"]
            lines.append(f"| {r['scene']} | {name} | {fc:.3f} | {b['forward_s']:.3f} | {b['backward_s']:.3f} "
                         f"| {b['forward_backward_s']:.3f} | {_fmt(b.get('speedup_vs_ref64'), '.1f')} "
                         f"| {_fmt(b.get('image_max_abs'))} | {_ties(b)}"
                         + (f" ({b['tie_pixels_differing']})" if "tie_pixels_differing" in b else "") + " "
                         f"| {_fmt(b.get('image_max_abs_all'))} | {_fmt(b.get('grad_rel_l2'))} "
                         f"| {_fmt(b.get('grad_worst_element'))} "
                         f"| {r['error_reference'] if name != r['error_reference'] else '(reference)'} |")
    return "\n".join(lines) + "\n"


def growth_exponents(results: list[dict]) -> dict:
    """Per backend, the slope of log(fwd+bwd time) against log(pixel-Gaussian pairs) (synthetic
    scenes with at least a second of 3 sizes; None with fewer than 3 points)."""
    pts: dict[str, list] = {}
    for r in results:
        if not r["scene"].startswith("synthetic") or "pixel_gaussian_pairs" not in r:
            continue
        for name, b in r["backends"].items():
            pts.setdefault(name, []).append((r["pixel_gaussian_pairs"], b["forward_backward_s"]))
    out = {}
    for name, p in pts.items():
        p = np.asarray(sorted(p), np.float64)
        out[name] = float(np.polyfit(np.log(p[:, 0]), np.log(p[:, 1]), 1)[0]) if len(p) >= 3 else None
    return out


def _plain(obj):
    """``obj`` with numpy scalars and arrays turned into Python numbers and lists (for JSON)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def targets(results: list[dict]) -> dict | None:
    """The targets (docs/performance.md) on the 50k / 504x378 scene, if it ran with ref64 and fast32 (and, when
    it ran, the same for fast32g under the key "fast32g")."""
    for r in results:
        if (r["n"], r["size"]) == TARGET_SCENE and r["scene"].startswith("synthetic"):
            b = r["backends"]
            if "ref64" not in b or "fast32" not in b:
                return None
            t = _targets_of(b["fast32"], r["size"])
            if "fast32g" in b:
                t["fast32g"] = _targets_of(b["fast32g"], r["size"])
            return t
    return None


def _targets_of(f: dict, size: str) -> dict:
    """One float32 row's targets (plain Python types, JSON-ready)."""
    px = np.prod(_parse_size(size))
    differing = f.get("tie_pixels_differing", 0) / px
    # no pixel needs excluding when the image is within the bound everywhere and the gradients of
    # the unmasked cotangent are too: then the tie target holds with zero excluded pixels
    all_px = f.get("image_max_abs_all")
    unmasked = f.get("grad_rel_l2_unmasked")
    no_exclusion = (all_px is not None and unmasked is not None and all_px <= TARGET_IMAGE_ERR
                    and unmasked <= TARGET_GRAD_REL_L2)
    return _plain({"speedup_fast32_vs_ref64": f["speedup_vs_ref64"],
                   "speedup_ok": f["speedup_vs_ref64"] >= TARGET_SPEEDUP,
                   "image_max_abs_outside_ties": f["image_max_abs"],
                   "image_ok": f["image_max_abs"] <= TARGET_IMAGE_ERR,
                   "tie_fraction": f["tie_pixels"] / px,
                   "ties_ok": f["tie_pixels"] / px <= TARGET_TIE_FRACTION,
                   "tie_pixels_differing_fraction": differing,
                   "tie_pixels_differing_ok": differing <= TARGET_TIE_FRACTION,
                   "grad_rel_l2": f["grad_rel_l2"],
                   "grad_ok": f["grad_rel_l2"] <= TARGET_GRAD_REL_L2,
                   "image_max_abs_all_pixels": all_px,
                   "grad_rel_l2_unmasked": unmasked,
                   "no_exclusion_needed": no_exclusion})


def plots(results: list[dict], exps: dict, out_dir: Path) -> list[Path]:
    """pareto.png (time against error, Pareto front per scene) and scaling.png (time against
    pairs with the fitted exponents)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = sorted({n for r in results for n in r["backends"]})
    colors = {n: plt.cm.tab10(i % 10) for i, n in enumerate(names)}
    written = []
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, key, title in ((axes[0], "image_max_abs", "image max |error| (outside ties)"),
                           (axes[1], "grad_rel_l2", "gradient relative L2 (worst field)")):
        for r in results:
            pts = [(b["forward_backward_s"], max(b[key], 1e-17), n) for n, b in r["backends"].items()
                   if key in b]
            for t, e, n in pts:
                ax.scatter(t, e, color=colors[n], s=25)
            front = sorted(pts)
            best, line = np.inf, []
            for t, e, _ in front:
                if e < best:
                    best = e
                    line.append((t, e))
            if len(line) > 1:
                ax.plot(*zip(*line), color="0.6", lw=0.8, zorder=0)
        ax.set_xscale("log"), ax.set_yscale("log")
        ax.set_xlabel("forward + backward seconds (median)"), ax.set_ylabel(title)
        ax.grid(True, which="both", alpha=0.3)
    for n in names:
        axes[0].scatter([], [], color=colors[n], label=n)
    axes[0].legend(fontsize=8)
    fig.suptitle("speed against error: each point a backend on a scene, grey the Pareto front per scene "
                 "(the reference itself has error 0 and is not drawn)", fontsize=10)
    fig.tight_layout()
    p = out_dir / "pareto.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    fig, ax = plt.subplots(figsize=(7, 5))
    for n in names:
        pts = sorted((r["pixel_gaussian_pairs"], r["backends"][n]["forward_backward_s"]) for r in results
                     if n in r["backends"] and "pixel_gaussian_pairs" in r and r["scene"].startswith("synthetic"))
        if pts:
            e = exps.get(n)
            ax.plot(*zip(*pts), "o-", color=colors[n],
                    label=f"{n} (exponent {e:.2f})" if e is not None else n)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("pixel-Gaussian pairs in covered tiles"), ax.set_ylabel("forward + backward seconds")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = out_dir / "scaling.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    return written


def _csv(results: list[dict]) -> str:
    buf = io.StringIO()
    cols = ["scene", "n", "size", "backend", "dtype", "forward_s", "backward_s", "forward_backward_s",
            "speedup_vs_ref64", "image_max_abs", "tie_pixels", "tie_pixels_differing", "grad_rel_l2",
            "grad_worst_element", "image_max_abs_all", "grad_rel_l2_unmasked",
            "error_reference", "first_forward_s", "first_backward_s", "pixel_gaussian_pairs"]
    wr = csv.writer(buf)
    wr.writerow(cols)
    for r in results:
        for name, b in r["backends"].items():
            wr.writerow([r["scene"], r["n"], r["size"], name, b["dtype"], b["forward_s"], b["backward_s"],
                         b["forward_backward_s"], b.get("speedup_vs_ref64"), b.get("image_max_abs"),
                         b.get("tie_pixels"), b.get("tie_pixels_differing"), b.get("grad_rel_l2"),
                         b.get("grad_worst_element"), b.get("image_max_abs_all"),
                         b.get("grad_rel_l2_unmasked"),
                         r["error_reference"], b["first_call"]["forward_s"],
                         b["first_call"]["backward_s"], r.get("pixel_gaussian_pairs")])
    return buf.getvalue()


def add_parser(sub) -> None:
    b = sub.add_parser("bench", help="speed against error of every available backend")
    b.add_argument("--n", type=int, nargs="*", default=list(DEFAULT_NS),
                   help="Gaussians of the synthetic scenes (none: only --fern-run)")
    b.add_argument("--size", nargs="+", default=list(DEFAULT_SIZES))
    b.add_argument("--backends", nargs="+", default=list(ALL_BACKENDS),
                   help="names of refgs.backends or module:object (default: all of "
                        f"{' '.join(ALL_BACKENDS)})")
    b.add_argument("--fern-run", help="a saved run directory: also bench its model.ply on its first test view")
    b.add_argument("--repeats", type=int, default=3)
    b.add_argument("--profile", default="inria", choices=("inria", "gsplat"))
    b.add_argument("--out", default="bench-out", help="folder for bench.json/.csv and the plots")
    b.add_argument("--no-plots", action="store_true")


def run(args, progress: bool = True) -> dict:
    """The ``refgs bench`` command; returns the JSON document it writes."""
    if args.repeats < 1:
        raise ConfigError(f"--repeats: expected at least 1, got {args.repeats}")
    if any(n < 1 for n in args.n):
        raise ConfigError(f"--n: expected positive numbers of Gaussians, got {args.n}")
    for s in args.size:
        _parse_size(s)
    if not args.n and not args.fern_run:
        raise ConfigError("--n: no synthetic scene and no --fern-run: nothing to measure")
    backends, unavailable = [], {}
    for name in args.backends:
        try:
            backends.append(bench_backend(name, args.profile))
        except BackendUnavailable as e:
            unavailable[name] = " ".join(e.reason.split())
    if not backends:
        raise ConfigError("--backends: none of the chosen backends can run here: " + json.dumps(unavailable))
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    info = machine_info()
    say = print if progress else (lambda *a, **k: None)
    say("# " + ", ".join(f"{k} {v}" for k, v in info.items()), flush=True)
    for name, why in unavailable.items():
        say(f"# {name}: n/a ({why})")
    scenes = list(synthetic_scenes(args.n, args.size))
    if args.fern_run:
        scenes.append(fern_scene(args.fern_run))
    results = []
    for label, n, size, g, cam in scenes:
        t0 = time.perf_counter()
        r = bench_scene(label, n, size, g, cam, backends, args.repeats, args.profile)
        results.append(r)
        say(f"{label}: {time.perf_counter() - t0:.1f} s"
            + (f" (not run: {', '.join(r['skipped'])}, above LIMITS)" if r["skipped"] else ""), flush=True)
    info["loadavg_after"] = list(os.getloadavg())
    exps = growth_exponents(results)
    doc = _plain({"info": info, "unavailable": unavailable, "limits": LIMITS, "results": results,
                  "growth_exponents": exps, "targets": targets(results)})
    atomic_write_json(out_dir / "bench.json", doc)
    atomic_write_text(out_dir / "bench.csv", _csv(results))
    if not args.no_plots:
        plots(results, exps, out_dir)
    say(table(results))
    say("growth exponent of fwd+bwd time in pixel-Gaussian pairs: "
        + ", ".join(f"{k} {_fmt(v, '.2f')}" for k, v in exps.items()))
    if doc["targets"] is not None:
        say("targets (50k, 504x378): " + json.dumps(doc["targets"]))
    say(f"peak memory (process max RSS): {peak_rss_gb():.2f} GB; written to {out_dir}")
    return doc


__all__ = ["run", "bench_backend", "BenchBackend", "bench_scene", "table", "growth_exponents",
           "targets", "LIMITS", "ALL_BACKENDS"]
