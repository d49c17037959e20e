"""Command line of the oracle (ORC-08).

    python -m oracle check --backend module:object [--clause ID ...] [--max-examples N]
                           [--seed S] [--report DIR] [--no-shrink] [--timeout S]
                           [--memory-limit MIB] [--known-differences FILE.toml] [--diagnose]
    python -m oracle list-clauses [--all]
    python -m oracle replay FILE.npz --backend module:object [--out DIR] [--timeout S]
    python -m oracle calibrate --backend module:object [--max-examples N] [--seed S]
    python -m oracle tolerances
    python -m oracle diagnose --backend module:object [--report DIR] [--max-examples N]
    python -m oracle matrix [--backend SPEC ...] [--report DIR] [--max-examples N]

``check``, ``replay``, ``diagnose`` and ``matrix`` run the backend in a worker process (oracle/isolation.py, ORC-11); the
module in ``--backend`` is imported there, with the current directory on sys.path, never in
this process.  ``check`` exits 0 exactly when every check is pass, n/a, not provided or a
declared known difference, 1 otherwise (fail, error, crash, timeout), 2 on a usage error (a
backend that cannot be loaded, an unknown clause, a bad known-differences file).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from . import __version__
from .isolation import DEFAULT_MEMORY_LIMIT_MIB, DEFAULT_TIMEOUT

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
                   help=f"folder for index.html, report.json, report.txt, pictures/ and failures/*.npz "
                        f"(default {DEFAULT_REPORT_DIR})")
    c.add_argument("--no-shrink", action="store_true", help="report the first failing example as found")
    c.add_argument("--quiet", action="store_true", help="print only the summary line")
    _worker_options(c)
    c.add_argument("--diagnose", action="store_true",
                   help="diagnose the failing checks (oracle/triage.py): which named deviations "
                        "explain them; writes diagnosis.json and shows it in index.html")
    c.add_argument("--known-differences", metavar="FILE",
                   help="TOML file of [[difference]] tables (check, clause, reason, link): failures "
                        "reported as 'known' (docs/oracle.md)")
    ls = sub.add_parser("list-clauses", help="the clauses the spec declares and the checks citing them")
    ls.add_argument("--all", action="store_true", help="also clauses with no check (method, oracle)")
    r = sub.add_parser("replay", help="re-run the check of a reproducer .npz against a backend")
    r.add_argument("file")
    r.add_argument("--backend", required=True)
    r.add_argument("--out", default=None, help="folder for the pictures (default: FILE's folder/<name>-replay)")
    _worker_options(r)
    k = sub.add_parser("calibrate", help="measure a backend's worst deviation per tolerance row")
    k.add_argument("--backend", required=True)
    k.add_argument("--max-examples", type=int, default=100)
    k.add_argument("--seed", type=int, default=0)
    sub.add_parser("tolerances", help="print the tolerance table (ORC-03) as Markdown")
    d = sub.add_parser("diagnose", help="which named deviations (docs/spec/deviations.md) explain "
                                        "a backend's failures (the backend runs in a worker)")
    d.add_argument("--backend", required=True)
    d.add_argument("--report", default=None, help="folder for diagnosis.json, diagnosis.txt and "
                                                  "diagnosis.html with its pictures")
    d.add_argument("--max-examples", type=int, default=6, help="scenes per check (default 6)")
    d.add_argument("--seed", type=int, default=0, help="hypothesis seed (default 0)")
    d.add_argument("--no-checks", action="store_true", help="judge on the deviations' witness scenes only")
    _worker_options(d)
    m = sub.add_parser("matrix", help="run several backends and tabulate their clause statuses "
                                      "(oracle/matrix.py, docs/conformance.md)")
    m.add_argument("--backend", action="append", default=[],
                   help="a column, module:object or registry name (repeatable; default: the shipped "
                        "and outside adapters)")
    m.add_argument("--clause", action="append", default=[], help="only checks citing these clauses")
    m.add_argument("--max-examples", type=int, default=10, help="hypothesis examples per check (default 10)")
    m.add_argument("--seed", type=int, default=0, help="hypothesis seed (default 0)")
    m.add_argument("--report", default="oracle-matrix", help="folder for matrix.md, matrix.json and "
                                                             "one report folder per column")
    m.add_argument("--no-shrink", action="store_true", help="report the first failing example as found")
    m.add_argument("--no-diagnose", action="store_true",
                   help="do not diagnose the columns' failing checks (oracle/triage.py)")
    _worker_options(m)
    return p


def _worker_options(p) -> None:
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT,
                   help=f"seconds of backend time one check may use before it is killed and marked "
                        f"timeout (default {DEFAULT_TIMEOUT:g}; 0: no limit)")
    p.add_argument("--memory-limit", type=int, default=DEFAULT_MEMORY_LIMIT_MIB, metavar="MIB",
                   help=f"data memory of the backend's worker process in MiB (default "
                        f"{DEFAULT_MEMORY_LIMIT_MIB}; 0: no limit); beyond it the check is a crash")


def _fail(msg: str) -> int:
    print(f"oracle: error: {msg}", file=sys.stderr)
    return 2


def cmd_check(a) -> int:
    from .checks import cited_clauses
    from .clauses import expand_selection
    from .known import load_file
    from .report import summary_text
    from .runner import Settings, run_isolated, write_reports

    if a.max_examples < 1:
        return _fail(f"--max-examples: expected a positive integer, got {a.max_examples}")
    if a.timeout < 0 or a.memory_limit < 0:
        return _fail("--timeout and --memory-limit: expected 0 (no limit) or a positive number")
    try:
        clauses = tuple(sorted(expand_selection(a.clause, cited_clauses()))) if a.clause else ()
        known = load_file(a.known_differences) if a.known_differences else ()
    except ValueError as exc:
        return _fail(str(exc))
    settings = Settings(max_examples=a.max_examples, seed=a.seed, shrink=not a.no_shrink,
                        report_dir=a.report, clauses=clauses, timeout=a.timeout or None,
                        memory_limit_mib=a.memory_limit, known_differences=known)

    def progress(r):
        if not a.quiet:
            print(f"  {r.check.name:<28} {r.status:<13} ({r.examples} examples, {r.duration:.1f} s)",
                  file=sys.stderr, flush=True)

    def diag_progress(name, status):
        if not a.quiet:
            print(f"  diagnosis: {name:<28} {status}", file=sys.stderr, flush=True)

    try:
        if a.diagnose:
            from .triage import run_diagnosed
            result = run_diagnosed(a.backend, settings, progress=progress,
                                   diagnosis_progress=diag_progress)
        else:
            result = run_isolated(a.backend, settings, progress=progress)
    except ValueError as exc:                   # the backend cannot be loaded; a bad known difference
        return _fail(str(exc))
    json_path, txt_path, page = write_reports(result, a.report)
    text = summary_text(result)
    print(text if not a.quiet else text.splitlines()[-1])
    print(f"report: {page} ({json_path}, {txt_path})")
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
    from pathlib import Path

    from .checks import get_check
    from .evaluate import Context, reference
    from .isolation import WorkerLost, open_backend
    from .pictures import draw
    from .report import load_case
    from .runner import safe_evaluate

    try:
        scene, meta = load_case(a.file)
        check = get_check(meta.get("check", ""))
        backend = open_backend(a.backend, a.memory_limit)
    except ValueError as exc:
        return _fail(str(exc))
    out = Path(a.out) if a.out else Path(a.file).with_name(Path(a.file).stem + "-replay")
    try:
        if str(scene.config.profile) != backend.profile:
            return _fail(f"{a.file}: scene is for profile {scene.config.profile!r}, backend renders {backend.profile!r}")
        s = scene.summary()
        print(f"replay {check.name} [{', '.join(check.clauses)}] on N={s['n_gaussians']}, "
              f"{s['width']}x{s['height']} px against {a.backend}")
        case = scene.rounded(backend.dtype)
        ctx = Context(backend, capture={})
        backend.session.begin_check(a.timeout or None)
        try:
            v = safe_evaluate(check, ctx, case)
        except WorkerLost as lost:
            print(f"  {lost.kind.upper()} {lost.reason}")
            pics = draw({"case": case, "forward": {"ref": reference(case)}}, out, check.name, note=lost.reason)
            print(f"pictures: {', '.join(str(out / p) for p, _ in pics)}")
            print(f"result: {lost.kind}")
            return 1
        for c in v.comparisons:
            print(f"  {'ok  ' if c.ok else 'FAIL'} {c.message}")
        pics = draw({"case": case, **ctx.capture}, out, check.name)
        if pics:
            print(f"pictures: {', '.join(str(out / p) for p, _ in pics)}")
        print("result: " + ("pass" if v.ok else "fail"))
        return 0 if v.ok else 1
    finally:
        backend.session.close()


def cmd_calibrate(a) -> int:
    from .calibrate import calibrate
    from .protocol import load_backend
    from .runner import Settings

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


def cmd_diagnose(a) -> int:
    from .diagnose import run_cli
    return run_cli(a)


def cmd_matrix(a) -> int:
    from .matrix import run_cli
    return run_cli(a)


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    np.seterr(all="ignore")
    return {"check": cmd_check, "list-clauses": cmd_list, "replay": cmd_replay,
            "calibrate": cmd_calibrate, "tolerances": cmd_tolerances, "diagnose": cmd_diagnose,
            "matrix": cmd_matrix}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
