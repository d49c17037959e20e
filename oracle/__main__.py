"""Command line of the oracle (ORC-08).

    python -m oracle check --backend module:object [--clause ID ...] [--max-examples N]
                           [--seed S] [--report DIR] [--no-shrink]
    python -m oracle list-clauses [--all]
    python -m oracle replay FILE.npz --backend module:object
    python -m oracle calibrate --backend module:object [--max-examples N] [--seed S]
    python -m oracle tolerances

``check`` exits 0 exactly when no clause failed ("not provided" and "n/a" do not fail), 1 when
some clause failed, 2 on a usage error (bad backend, unknown clause).  The module in
``--backend`` is imported with the current directory on sys.path.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from . import __version__

DEFAULT_REPORT_DIR = "oracle-report"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m oracle", description=(
        "Conformance testing of a 3DGS backend against refgs (docs/oracle.md)."))
    p.add_argument("--version", action="version", version=f"oracle {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="run the conformance checks against a backend")
    c.add_argument("--backend", required=True, help="module:object, e.g. "
                   "oracle.adapters.refgs_backend:refgs_float32")
    c.add_argument("--clause", action="append", default=[],
                   help="only checks citing these clause ids or prefixes (repeatable, or a comma list)")
    c.add_argument("--max-examples", type=int, default=20, help="hypothesis examples per check (default 20)")
    c.add_argument("--seed", type=int, default=0, help="hypothesis seed (default 0)")
    c.add_argument("--report", default=DEFAULT_REPORT_DIR,
                   help=f"folder for report.json, report.txt and failures/*.npz (default {DEFAULT_REPORT_DIR})")
    c.add_argument("--no-shrink", action="store_true", help="report the first failing example as found")
    c.add_argument("--quiet", action="store_true", help="print only the summary line")
    ls = sub.add_parser("list-clauses", help="the clauses the spec declares and the checks citing them")
    ls.add_argument("--all", action="store_true", help="also clauses with no check (method, oracle)")
    r = sub.add_parser("replay", help="re-run the check of a reproducer .npz against a backend")
    r.add_argument("file")
    r.add_argument("--backend", required=True)
    k = sub.add_parser("calibrate", help="measure a backend's worst deviation per tolerance row")
    k.add_argument("--backend", required=True)
    k.add_argument("--max-examples", type=int, default=100)
    k.add_argument("--seed", type=int, default=0)
    sub.add_parser("tolerances", help="print the tolerance table (ORC-03) as Markdown")
    return p


def _fail(msg: str) -> int:
    print(f"oracle: error: {msg}", file=sys.stderr)
    return 2


def cmd_check(a) -> int:
    from .checks import cited_clauses
    from .clauses import expand_selection
    from .protocol import load_backend
    from .report import summary_text, write_report
    from .runner import Settings, run

    if a.max_examples < 1:
        return _fail(f"--max-examples: expected a positive integer, got {a.max_examples}")
    try:
        backend = load_backend(a.backend)
        clauses = tuple(sorted(expand_selection(a.clause, cited_clauses()))) if a.clause else ()
    except ValueError as exc:
        return _fail(str(exc))
    settings = Settings(max_examples=a.max_examples, seed=a.seed, shrink=not a.no_shrink,
                        report_dir=a.report, clauses=clauses)

    def progress(r):
        if not a.quiet:
            print(f"  {r.check.name:<28} {r.status:<13} ({r.examples} examples, {r.duration:.1f} s)",
                  file=sys.stderr, flush=True)

    result = run(backend, settings, progress=progress)
    json_path, txt_path = write_report(result, a.report)
    text = summary_text(result)
    print(text if not a.quiet else text.splitlines()[-1])
    print(f"report: {json_path} and {txt_path}")
    return result.exit_status


def cmd_list(a) -> int:
    from .checks import CHECKS
    from .clauses import RENDERER_PREFIXES, clause_sort_key, load_clauses

    clauses = load_clauses()
    by = {}
    for c in CHECKS:
        for cid in c.clauses:
            by.setdefault(cid, []).append(c.name + (" (reference-only)" if c.kind == "reference" else ""))
    ids = sorted(set(clauses) | set(by), key=clause_sort_key)
    for cid in ids:
        if not a.all and cid.split("-")[0] not in RENDERER_PREFIXES and cid not in by:
            continue
        title = clauses[cid].title if cid in clauses else "(not declared in docs/spec)"
        checks = ", ".join(by.get(cid, [])) or "(no check)"
        print(f"{cid:<9}{title}\n{'':<9}checks: {checks}")
    return 0


def cmd_replay(a) -> int:
    from .checks import get_check
    from .evaluate import Context
    from .protocol import load_backend
    from .report import load_scene

    try:
        scene, meta = load_scene(a.file)
        backend = load_backend(a.backend)
        check = get_check(meta.get("check", ""))
    except ValueError as exc:
        return _fail(str(exc))
    if str(scene.config.profile) != backend.profile:
        return _fail(f"{a.file}: scene is for profile {scene.config.profile!r}, backend renders {backend.profile!r}")
    ctx = Context(backend)
    v = check.evaluate(ctx, scene.rounded(backend.dtype))
    s = scene.summary()
    print(f"replay {check.name} [{', '.join(check.clauses)}] on N={s['n_gaussians']}, "
          f"{s['width']}x{s['height']} px against {a.backend}")
    for c in v.comparisons:
        print(f"  {'ok  ' if c.ok else 'FAIL'} {c.message}")
    print("result: " + ("pass" if v.ok else "fail"))
    return 0 if v.ok else 1


def cmd_calibrate(a) -> int:
    from .protocol import load_backend
    from .runner import Settings, calibrate

    try:
        backend = load_backend(a.backend)
    except ValueError as exc:
        return _fail(str(exc))
    worst = calibrate(backend, Settings(max_examples=a.max_examples, seed=a.seed),
                      progress=lambda c: print(f"  measured {c.name}", file=sys.stderr, flush=True))
    print(f"calibration of {a.backend} ({backend.dtype}, {backend.profile}), "
          f"{a.max_examples} examples per check, seed {a.seed}")
    print(f"{'stage':<11}{'output':<16}{'n':>5} {'atol now':>9} {'needed':>9}  {'rel_l2':>8} "
          f"{'1-cos':>8} {'magratio':>8} {'in band':>8} {'flips':>6}  worst check")
    for (stage, label), r in sorted(worst.items()):
        t = r["tol"]
        print(f"{stage:<11}{label:<16}{r['n']:>5} {t.atol:>9.1e} {r['atol_needed']:>9.2e}  "
              f"{r['rel_l2']:>8.1e} {r['one_minus_cosine']:>8.1e} {r['mag_ratio']:>8.3f} "
              f"{r['in_band']:>8d} {r['flips']:>6d}  {r['worst_check']}")
    return 0


def cmd_tolerances(a) -> int:
    from .tolerances import markdown_table
    sys.stdout.write(markdown_table())
    return 0


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    np.seterr(all="ignore")
    return {"check": cmd_check, "list-clauses": cmd_list, "replay": cmd_replay,
            "calibrate": cmd_calibrate, "tolerances": cmd_tolerances}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
