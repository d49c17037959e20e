"""Which test views make a difference between two methods: the paired difference per held-out
view over seeds (FM-16), from the records' ``metrics.json`` ``per_view`` lists.

    python -m refgs.analysis.per_view RUN_OR_RECORD [...] --method fm --baseline 3dgs
        [--metric psnr] [--subset NAME ...] [--scene SCENE_DIR]

The folders must be one scene and view count (runs or records of ``refgs record``), two method
labels (refgs.analysis.tables.method_label) and the same seeds.  For each test view, in the order
of the runs' ``test_images``: the baseline's and the method's mean over the seeds, and the
paired difference method − baseline seed by seed with its Student-t 95 % CI and p
(refgs.analysis.stats.paired_stats).  Then the mean over all views (the number the main table
reports: the metrics are means of per-view values) and, with ``--subset``, the mean over the
named views only.  A subset chosen after seeing the per-view numbers is an exploratory reading,
not a test: the table says so.  With ``--scene`` (the scene folder, its COLMAP model read as in
training, DAT-01) each view also gets its nearest training view and the distance between their
camera centres, in the model's units: a held-out view next to a training view measures fidelity
to the training views more than generalisation.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..errors import ConfigError, RefgsError
from ..runs import CONFIG_FILE, METRICS_FILE
from .report_tables import diff_cells
from .stats import CONFIDENCE, paired_stats
from .tables import method_label, read_run_json

#: metrics.json per-view keys that can be compared, with the decimals shown
PER_VIEW_METRICS = {"psnr": 2, "ssim": 3, "lpips_vgg": 3}
SUBSET_NOTE = "chosen after seeing the per-view numbers: exploratory, not a test"


def load(folders) -> dict[tuple[str, int], dict]:
    """{(label, seed): {"scene", "views", "names", "per_view"}} of the folders; ConfigError
    naming the folder for a missing per-view list or a second run of one label and seed."""
    out = {}
    for f in map(Path, folders):
        cfg, met = read_run_json(f / CONFIG_FILE), read_run_json(f / METRICS_FILE)
        s = cfg.get("settings") or {}
        pv = met.get("per_view")
        if not isinstance(pv, list) or not pv:
            raise ConfigError(f"{f / METRICS_FILE}: no per_view list")
        key = (method_label(s), int(s.get("seed", -1)))
        if key in out:
            raise ConfigError(f"{f}: a second run of {key[0]} at seed {key[1]} (the first: "
                              f"{out[key]['folder']})")
        out[key] = {"scene": Path(str(s.get("scene"))).name, "views": s.get("views"),
                    "names": [v.get("name") for v in pv], "per_view": pv, "folder": str(f),
                    "train": list(cfg.get("train_images") or [])}
    return out


def pairs(runs: dict, method: str, baseline: str) -> list[tuple[dict, dict]]:
    """(baseline run, method run) per seed both have, seeds ascending; ConfigError when the
    runs are of several scenes or their test views differ."""
    seeds = sorted({s for lab, s in runs if lab == method} & {s for lab, s in runs if lab == baseline})
    if not seeds:
        raise ConfigError(f"no seed has both {method!r} and {baseline!r} (labels present: "
                          f"{sorted({lab for lab, _ in runs})})")
    out = [(runs[(baseline, s)], runs[(method, s)]) for s in seeds]
    first = out[0][0]
    for b, m in out:
        for r in (b, m):
            if ((r["scene"], r["views"], r["names"], r["train"])
                    != (first["scene"], first["views"], first["names"], first["train"])):
                raise ConfigError(f"{r['folder']}: scene, views or test views differ from "
                                  f"{first['folder']}")
    return out


def nearest_training_views(scene_dir, names: list, train: list) -> dict[str, tuple[str, float]]:
    """{test view: (nearest training view, distance between the camera centres)} from the COLMAP
    model of ``scene_dir`` (matched by file stem, as refgs.data.colmap.load_scene does)."""
    from ..data.colmap import read_model

    rec = read_model(Path(scene_dir) / "sparse" / "0")
    centres = {Path(im.name).stem: np.asarray(im.projection_center(), np.float64)
               for im in rec.images.values() if im.has_pose}
    missing = [n for n in names + train if Path(n).stem not in centres]
    if missing or not train:
        raise ConfigError(f"{scene_dir}: no posed model image for {missing or 'the training views'}")
    out = {}
    for n in names:
        d = {t: float(np.linalg.norm(centres[Path(n).stem] - centres[Path(t).stem])) for t in train}
        out[n] = min(d.items(), key=lambda kv: kv[1])
    return out


def _values(run: dict, metric: str, idx) -> np.ndarray:
    try:
        return np.array([float(run["per_view"][i][metric]) for i in idx])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{run['folder']}/{METRICS_FILE}: per_view lacks {metric}") from None


def row(label: str, pr: list, metric: str, idx, extra: str = "") -> str:
    dec = PER_VIEW_METRICS[metric]
    base = [float(_values(b, metric, idx).mean()) for b, _ in pr]
    meth = [float(_values(m, metric, idx).mean()) for _, m in pr]
    diff, p, _ = diff_cells(paired_stats(np.subtract(meth, base)), dec)
    return f"| {label} |{extra} {np.mean(base):.{dec}f} | {np.mean(meth):.{dec}f} | {diff} | {p} |"


def per_view_markdown(folders, method: str, baseline: str, metric: str = "psnr",
                      subset=(), scene=None) -> str:
    if metric not in PER_VIEW_METRICS:
        raise ConfigError(f"--metric: expected one of {sorted(PER_VIEW_METRICS)}, got {metric!r}")
    pr = pairs(load(folders), method, baseline)
    names = pr[0][0]["names"]
    missing = [v for v in subset if v not in names]
    if missing:
        raise ConfigError(f"--subset: {missing} are not test views (the views: {names})")
    near = nearest_training_views(scene, names, pr[0][0]["train"]) if scene else None
    head = (f"| test view |{' nearest training view (camera distance) |' if near else ''} "
            f"{baseline} | {method} | Δ {metric} {method} − {baseline} "
            f"[{round(100 * CONFIDENCE)} % CI] | p |")
    lines = [f"{pr[0][0]['scene']}, {pr[0][0]['views']} views; {len(pr)} paired seeds", "",
             head, "|---|" + "---|" * (5 if near else 4)]
    for i, n in enumerate(names):
        extra = f" `{near[n][0]}` ({near[n][1]:.3g}) |" if near else ""
        lines.append(row(f"`{n}`", pr, metric, [i], extra))
    blank = " |" if near else ""
    lines.append(row("mean of all views", pr, metric, range(len(names)), blank))
    if subset:
        lines.append(row(f"mean of {', '.join(f'`{v}`' for v in subset)} ({SUBSET_NOTE})", pr,
                         metric, [names.index(v) for v in subset], blank))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m refgs.analysis.per_view",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", help="runs or records of one scene and view count")
    ap.add_argument("--method", required=True, help="method label (e.g. fm)")
    ap.add_argument("--baseline", required=True, help="baseline label (e.g. 3dgs)")
    ap.add_argument("--metric", default="psnr", help=f"one of {sorted(PER_VIEW_METRICS)}")
    ap.add_argument("--subset", nargs="+", default=[], metavar="VIEW",
                    help="also the mean over these test views (file names)")
    ap.add_argument("--scene", default=None,
                    help="the scene folder: add each view's nearest training view (camera centres)")
    args = ap.parse_args(argv)
    try:
        sys.stdout.write(per_view_markdown(args.folders, args.method, args.baseline,
                                           args.metric, args.subset, args.scene))
    except RefgsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
