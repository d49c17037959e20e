"""Benchmark refgs.fast against the float64 reference on the seeded benchmark scene (docs/fast.md).

    python -m refgs.fast.bench --n 10000 50000 --size 504x378 --repeats 3 [--json out.json]

For each N: the first call of each fast variant (numba compilation or on-disk cache load) is
timed separately; then ``--repeats`` rounds, each timing in turn the reference float64, fast
float64 and fast float32 forward and backward (interleaved, so a changing machine load hits all
three alike), with time.perf_counter (wall) and time.process_time (CPU of all threads).  Medians
are reported, with the ratios reference / fast from the same run, the machine's load average
before and after, and the accuracy of both fast variants against the reference:

* fast float64: max |difference| of image / alpha / depth, n_contrib and radii equality, gradient
  relative L2 error per field;
* fast float32: image max |error| outside the near-tie pixels of refgs.fast.ties (which are
  counted by reason, with the number that actually differ by more than 1e-5), and gradient
  relative L2 with the cotangent zeroed on the near-tie pixels and the kink-tied Gaussian rows
  excluded (counted).

The cotangent is the seeded normal v_image of a loss L = <v_image, image>.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numba
import numpy as np

import refgs

from ..io.atomic import atomic_write_text
from ..synthetic import benchmark_scene
from .render import render, render_backward
from .ties import find_ties

#: seed of the cotangent v_image
COTANGENT_SEED = 1
#: the float32 image error target outside near-ties (docs/performance.md, "Targets")
IMAGE_TOL_F32 = 1e-5
GRAD_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d")


def _timed(fn, *args):
    w, c = time.perf_counter(), time.process_time()
    r = fn(*args)
    return r, time.perf_counter() - w, time.process_time() - c


def _rel_l2(a, b, rows=None) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if rows is not None:
        a, b = a[rows], b[rows]
    nb = np.linalg.norm(b)
    return float(np.linalg.norm(a - b) / nb) if nb > 0 else float(np.linalg.norm(a))


def run_one(n: int, width: int, height: int, repeats: int, profile: str = "inria") -> dict:
    g64, cam = benchmark_scene(n, width, height, seed=0)
    g32 = g64.astype(np.float32)
    cfg = refgs.RenderConfig(profile=profile)
    v = np.random.default_rng(COTANGENT_SEED).normal(size=(height, width, 3))
    res = {"n": n, "size": f"{width}x{height}", "profile": profile, "first_call": {}}
    for name, g in (("fast64", g64), ("fast32", g32)):
        out, wf, _ = _timed(render, g, cam, cfg)
        _, wb, _ = _timed(render_backward, out, v)
        res["first_call"][name] = {"forward_s": wf, "backward_s": wb}
    times = {k: {"fwd": [], "bwd": [], "fwd_cpu": [], "bwd_cpu": []}
             for k in ("ref64", "fast64", "fast32")}
    outs = {}
    for _ in range(repeats):
        for name, fwd, bwd, g in (("ref64", refgs.render, refgs.render_backward, g64),
                                  ("fast64", render, render_backward, g64),
                                  ("fast32", render, render_backward, g32)):
            out, wf, cf = _timed(fwd, g, cam, cfg)
            grads, wb, cb = _timed(bwd, out, v)
            t = times[name]
            t["fwd"].append(wf), t["bwd"].append(wb), t["fwd_cpu"].append(cf), t["bwd_cpu"].append(cb)
            outs[name] = (out, grads)
    med = {k: {m: statistics.median(x) for m, x in t.items()} for k, t in times.items()}
    for k in med:
        med[k]["fwd_bwd"] = statistics.median(np.add(times[k]["fwd"], times[k]["bwd"]))
        med[k]["fwd_bwd_cpu"] = statistics.median(np.add(times[k]["fwd_cpu"], times[k]["bwd_cpu"]))
    res["median_s"] = med
    res["all_s"] = times
    res["speedup_vs_ref64"] = {k: {"forward": med["ref64"]["fwd"] / med[k]["fwd"],
                                   "forward_backward": med["ref64"]["fwd_bwd"] / med[k]["fwd_bwd"],
                                   "forward_backward_cpu":
                                       med["ref64"]["fwd_bwd_cpu"] / med[k]["fwd_bwd_cpu"]}
                               for k in ("fast64", "fast32")}
    ref, gref = outs["ref64"]
    o64, g64f = outs["fast64"]
    res["accuracy_fast64"] = {
        **{f"{k}_max_abs": float(np.max(np.abs(getattr(o64, k) - getattr(ref, k))))
           for k in ("image", "alpha", "depth")},
        "n_contrib_equal": bool(np.array_equal(o64.n_contrib, ref.n_contrib)),
        "radii_equal": bool(np.array_equal(o64.radii, ref.radii)),
        "grad_rel_l2": {k: _rel_l2(getattr(g64f, k), getattr(gref, k)) for k in GRAD_FIELDS}}
    o32, _ = outs["fast32"]
    ties = find_ties(o64)
    err = np.max(np.abs(o32.image.astype(np.float64) - ref.image), axis=-1)
    fwd_mask, bwd_mask = ties["forward"], ties["backward"]
    v_masked = np.where(bwd_mask[..., None], 0.0, v)
    gref_m = refgs.render_backward(ref, v_masked)
    g32_m = render_backward(o32, v_masked)
    rows = ~ties["kink_gaussians"]
    res["accuracy_fast32"] = {
        "image_max_abs_outside_ties": float(np.max(np.where(fwd_mask, 0, err))),
        "image_max_abs_all": float(err.max()),
        "pixels": int(err.size),
        "tie_pixels_forward": int(fwd_mask.sum()), "tie_pixels_backward": int(bwd_mask.sum()),
        "tie_counts": ties["counts"],
        "tie_pixels_over_tol": int(np.sum(fwd_mask & (err > IMAGE_TOL_F32))),
        "pixels_over_tol_outside_ties": int(np.sum(~fwd_mask & (err > IMAGE_TOL_F32))),
        "n_contrib_differ": int(np.sum(o32.n_contrib != ref.n_contrib)),
        "grad_rel_l2_masked": {k: _rel_l2(getattr(g32_m, k), getattr(gref_m, k), rows)
                               for k in GRAD_FIELDS},
        "gaussians_excluded_kink": int((~rows).sum())}
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--size", default="504x378")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", default="inria", choices=["inria", "gsplat"])
    ap.add_argument("--json", help="write the full results here")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats: expected at least 1")
    w, h = (int(x) for x in args.size.lower().split("x"))
    info = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "numba_threads": numba.get_num_threads(), "numba": numba.__version__,
            "numpy": np.__version__, "loadavg_before": os.getloadavg()}
    print("# " + ", ".join(f"{k} {v}" for k, v in info.items()), flush=True)
    results = []
    for n in args.n:
        r = run_one(n, w, h, args.repeats, args.profile)
        results.append(r)
        m, s = r["median_s"], r["speedup_vs_ref64"]
        fc = {k: f"{v['forward_s']:.2f}/{v['backward_s']:.2f} s" for k, v in r["first_call"].items()}
        print(f"N={n} {r['size']} {args.profile}: first call fwd/bwd fast64 {fc['fast64']}, "
              f"fast32 {fc['fast32']}")
        for k in ("ref64", "fast64", "fast32"):
            print(f"  {k:7s} fwd {m[k]['fwd']:8.3f} s  fwd+bwd {m[k]['fwd_bwd']:8.3f} s  "
                  f"(cpu {m[k]['fwd_bwd_cpu']:.3f} s)" + ("" if k == "ref64" else
                  f"  speedup fwd {s[k]['forward']:.1f}x  fwd+bwd {s[k]['forward_backward']:.1f}x "
                  f"(cpu {s[k]['forward_backward_cpu']:.1f}x)"))
        print("  fast64 accuracy: " + json.dumps(r["accuracy_fast64"]))
        print("  fast32 accuracy: " + json.dumps(r["accuracy_fast32"]), flush=True)
    info["loadavg_after"] = os.getloadavg()
    print(f"# loadavg after {info['loadavg_after']}")
    if args.json:
        atomic_write_text(args.json, json.dumps({"info": info, "results": results}, indent=1))


if __name__ == "__main__":
    main()
