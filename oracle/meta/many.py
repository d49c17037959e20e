"""Meta-test at scale: many deviations at once, and defects the catalogue does not name (DEV-03).

Seeded random sets of compatible catalogue deviations are switched on in refgs (a deviant
backend, oracle/meta/deviant.py), and sets with one or two off-catalogue defects on top
(oracle/meta/offcatalogue.py); each is diagnosed on the stage probes and the witnesses
(oracle/diagnose.py with no check scenes) and scored: recall and precision of the named set
against the planted one, and, for each off-catalogue defect, whether the report names its stage.

    python -m oracle.meta.many --sizes 4 6 8 10 12 --sets 20 --seed 0 [--out table.md] [--rows rows.json]
    python -m oracle.meta.many --table-from rows-a.json rows-b.json     # the table of several runs

prints one line per set as it goes and the table at the end (docs/spec/deviations.md holds it);
runs may be split by size (``--sizes 8``; ``--sizes`` alone: the off-catalogue sets only).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

import refgs
from refgs.deviations import DEVIATIONS, incompatible
from refgs.io.atomic import atomic_write_json, atomic_write_text

from ..diagnose import diagnose
from .deviant import deviant, observable_names
from .offcatalogue import DEFECTS, OffCatalogue

#: catalogue deviations planted beside the off-catalogue defects (an image-only renderer has no
#: backward: forward deviations only, and only those whose witness shows in image or alpha)
OFF_SIZES = (4, 6)


def image_observable() -> list[str]:
    """Forward deviations whose witness changes the image or the alpha (not only radii)."""
    out = []
    for n in observable_names():
        d = DEVIATIONS[n]
        if d.backward_only:
            continue
        g, cam, cfg = d.witness.build()
        a = refgs.render(g, cam, cfg)
        b = refgs.render(g, cam, dataclasses.replace(cfg, deviations=frozenset({n})))
        if not (np.array_equal(a.image, b.image) and np.array_equal(a.alpha, b.alpha)):
            out.append(n)
    return out


#: ten catalogue deviations at once (``python -m oracle diagnose --backend
#: oracle.meta.many:ten_deviations``: the timing of docs/spec/deviations.md)
ten_deviations = deviant("quat_xyzw", "rotation_transposed", "no_frustum_clamp", "no_dilation",
                         "radius_3sigma", "colour_clamp_01", "pixel_centre_0", "alpha_cap_0.999",
                         "alpha_skip_off", "stop_off")
#: an image-only renderer as an outside author writes one: seven catalogue deviations and three
#: defects the catalogue does not name (in the covariance, the projected ellipse, the sort key)
outside_like = OffCatalogue({"quat_xyzw", "no_frustum_clamp", "no_dilation", "sh_dir_reversed",
                             "pixel_centre_0", "alpha_skip_off", "stop_off"},
                            {"cov_rotation_sign", "ellipse_mirrored", "sort_by_distance"})


def compatible_set(rng: np.random.Generator, size: int, names) -> frozenset:
    """``size`` compatible names drawn from ``names`` in a random order (greedy; redrawn until
    the size is reached)."""
    while True:
        out: set = set()
        for n in rng.permutation(list(names)).tolist():
            if incompatible(out | {n}) is None:
                out.add(n)
                if len(out) == size:
                    return frozenset(out)


def catalogue_sets(size: int, count: int, seed: int) -> list[frozenset]:
    """``count`` distinct compatible sets of ``size`` observable deviations, seeded."""
    rng = np.random.default_rng([seed, size])
    out: list = []
    while len(out) < count:
        s = compatible_set(rng, size, observable_names())
        if s not in out:
            out.append(s)
    return out


def off_catalogue_sets(seed: int) -> list[tuple[frozenset, frozenset]]:
    """(deviations, defects): every defect alone and every pair of defects of different
    stages, each beside a seeded set of forward deviations of size OFF_SIZES (alternating)."""
    rng = np.random.default_rng([seed, 99])
    forward = image_observable()
    names = sorted(DEFECTS)
    combos = [frozenset({d}) for d in names] + [frozenset({a, b}) for i, a in enumerate(names)
                                                 for b in names[i + 1:]]
    return [(compatible_set(rng, OFF_SIZES[k % len(OFF_SIZES)], forward), c) for k, c in enumerate(combos)]


def score(planted, found) -> dict:
    """True positives, how many planted and named; recall and precision (1 when nothing is
    named)."""
    planted, found = set(planted), set(found)
    tp = len(planted & found)
    return {"tp": tp, "n_planted": len(planted), "n_named": len(found),
            "recall": tp / len(planted) if planted else 1.0, "precision": tp / len(found) if found else 1.0}


def run_set(deviations, defects=frozenset()) -> dict:
    """Diagnose one planted renderer (stage probes and witnesses, no check scenes)."""
    backend = OffCatalogue(deviations, defects) if defects else deviant(*sorted(deviations))
    t0 = time.perf_counter()
    r = diagnose(backend, checks=[], verify_set=False)
    row = {"planted": sorted(deviations), "defects": sorted(defects), "found": r["deviations"],
           **score(deviations, r["deviations"]), "seconds": round(time.perf_counter() - t0, 1),
           "residual_stages": r["residual"]["stages"], "residual": r["residual"]["summary"]}
    row["defect_stages_named"] = {d: DEFECTS[d][0] in r["residual"]["stages"] for d in defects}
    return row


def table(rows: list[dict]) -> str:
    """The Markdown table: per size (catalogue only) and per off-catalogue kind."""
    lines = ["| planted | sets | recall | precision | exact sets | defects' stage named | "
             "s per set (median) |", "|---|---|---|---|---|---|---|"]
    groups: dict = {}
    for r in rows:
        key = (f"{len(r['planted'])} catalogue" if not r["defects"] else
               f"{len(r['planted'])} catalogue + {len(r['defects'])} off-catalogue")
        groups.setdefault(key, []).append(r)
    for key in sorted(groups, key=lambda k: (" + " in k, int(k.split()[0]), k)):
        g = groups[key]
        tp, pl, nm = (sum(r[k] for r in g) for k in ("tp", "n_planted", "n_named"))
        exact = sum(r["tp"] == r["n_planted"] == r["n_named"] for r in g)
        named = [v for r in g for v in r["defect_stages_named"].values()]
        lines.append(f"| {key} | {len(g)} | {tp / pl:.1%} | {tp / nm if nm else 1:.1%} | "
                     f"{exact} of {len(g)} | "
                     f"{f'{sum(named)} of {len(named)}' if named else '-'} | "
                     f"{float(np.median([r['seconds'] for r in g])):.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oracle.meta.many", description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[4, 6, 8, 10, 12],
                    help="sizes of the catalogue sets (none: off-catalogue sets only)")
    ap.add_argument("--sets", type=int, default=20, help="catalogue sets per size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-off-catalogue", action="store_true")
    ap.add_argument("--out", help="write the table (Markdown) here")
    ap.add_argument("--rows", help="write every set's row here (JSON, rewritten after each set); "
                                   "sets already in it are not run again")
    ap.add_argument("--table-from", nargs="+", metavar="ROWS",
                    help="print the table of rows written by earlier runs (--rows files) and stop")
    a = ap.parse_args(argv)
    if a.table_from:
        rows = [r for f in a.table_from for r in json.loads(Path(f).read_text())]
        text = table(rows) + f"\n{len(rows)} sets (seed {a.seed}).\n"
        print(text)
        if a.out:
            atomic_write_text(a.out, text)
        return 0
    if a.sets < 1 or any(s < 1 for s in a.sizes) or (not a.sizes and a.no_off_catalogue):
        print("oracle.meta.many: error: --sets and --sizes: expected positive integers (and some "
              "sets to run)", file=sys.stderr)
        return 2
    jobs = [(s, frozenset()) for size in a.sizes for s in catalogue_sets(size, a.sets, a.seed)]
    if not a.no_off_catalogue:
        jobs += off_catalogue_sets(a.seed)
    rows = json.loads(Path(a.rows).read_text()) if a.rows and Path(a.rows).is_file() else []
    done = {(tuple(r["planted"]), tuple(r["defects"])) for r in rows}
    t0 = time.perf_counter()
    for k, (devs, defects) in enumerate(jobs):
        if (tuple(sorted(devs)), tuple(sorted(defects))) in done:
            continue
        r = run_set(devs, defects)
        rows.append(r)
        if a.rows:
            atomic_write_json(a.rows, rows)
        miss, extra = sorted(set(r["planted"]) - set(r["found"])), sorted(set(r["found"]) - set(r["planted"]))
        print(f"[{k + 1}/{len(jobs)}] {len(devs)} + {r['defects'] or 'none'}: {r['seconds']} s; "
              f"missed {miss}, extra {extra}; {r['residual']}", flush=True)
    text = table(rows) + (f"\n{len(rows)} sets in {time.perf_counter() - t0:.0f} s (seed {a.seed}).\n")
    print(text)
    if a.out:
        atomic_write_text(a.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["catalogue_sets", "compatible_set", "image_observable", "off_catalogue_sets", "outside_like",
           "run_set", "score", "table", "ten_deviations"]
