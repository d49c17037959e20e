"""The conformance matrix: one column per backend, one row per clause (docs/conformance.md).

    python -m oracle matrix [--backend SPEC ...] [--clause ID ...] [--max-examples N] [--seed S]
                            [--report DIR] [--no-shrink] [--timeout S] [--memory-limit MIB]

Each backend runs in its own worker process (oracle/isolation.py, ``run_isolated``) with the same
settings, and gets its full report in ``DIR/<column>/`` (index.html, report.json, report.txt,
failures/).  A backend that cannot be loaded here (a package not installed) is a column of
``unavailable`` cells with the one-line reason.  The matrix is a measurement: the command exits 0
once ``matrix.json`` and ``matrix.md`` are written, 2 on a usage error; each column records its
own ``check`` exit status.

    matrix.json   {"schema", "settings", "columns": [{spec, name, version, profile, dtype,
                  unavailable_reason, load_error, exit_status, report, summary}],
                  "clauses": {id: {title, cells: [{status, worst_ratio}]}}}
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

from refgs.io.atomic import atomic_write_json, atomic_write_text

from .clauses import clause_sort_key, load_clauses
from .protocol import BackendError
from .report import STATUS_ORDER, clause_table, write_report

SCHEMA = "refgs-oracle-matrix/1"
#: the columns of ``python -m oracle matrix`` without --backend: refgs (both profiles, float64 and
#: float32), the torch transcription, gsplat 1.5.3, and the outside renderers of docs/conformance.md
DEFAULT_COLUMNS = (
    "oracle.adapters.refgs_backend:refgs_float64",
    "oracle.adapters.refgs_backend:refgs_float32",
    "oracle.adapters.refgs_backend:refgs_gsplat_float32",
    "oracle.adapters.torch_backend:torch_float32",
    "oracle.adapters.gsplat_backend:gsplat_backend",
    "oracle.adapters.gswarp_backend:gswarp_float32",
    "oracle.adapters.taichi_splatting_backend:taichi_float32",
    "oracle.adapters.taichi_splatting_backend:taichi_float64",
)
#: a cell of a backend that could not be loaded
UNAVAILABLE = "unavailable"


def column_slug(spec: str) -> str:
    """A folder name for ``spec``: its object name, else the module's last part."""
    mod, _, obj = spec.partition(":")
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", obj or mod.rsplit(".", 1)[-1]) or "backend"


def build_matrix(specs, settings, report_dir, progress=None) -> dict:
    """Run every backend of ``specs`` (oracle/runner.py ``Settings``; its report_dir is replaced
    per column) and return the matrix dict (module docstring); writes each column's report."""
    from dataclasses import replace

    from .runner import run_isolated

    root = Path(report_dir)
    clauses = load_clauses()
    columns, tables = [], []
    for spec in specs:
        folder = root / column_slug(spec)
        col = {"spec": spec, "report": str(folder)}
        try:
            result = run_isolated(spec, replace(settings, report_dir=str(folder)))
        except BackendError as exc:
            col.update(load_error=str(exc), exit_status=None)
            columns.append(col)
            tables.append(None)
            if progress is not None:
                progress(spec, f"{UNAVAILABLE}: {exc}")
            continue
        write_report(result, folder)
        be = result.backend
        table = clause_table(result.results, result.clauses)
        col.update(name=be.name, version=be.version, profile=be.profile, dtype=be.dtype,
                   unavailable_reason=be.unavailable_reason, load_error=None,
                   exit_status=result.exit_status,
                   summary={s: sum(1 for r in table.values() if r["status"] == s) for s in STATUS_ORDER})
        columns.append(col)
        tables.append(table)
        if progress is not None:
            progress(spec, f"exit {result.exit_status} in {result.duration:.1f} s")
    ids = sorted({cid for t in tables if t for cid in t}, key=clause_sort_key)
    rows = {}
    for cid in ids:
        cells = []
        for t in tables:
            row = None if t is None else t.get(cid)
            if t is None:
                cells.append({"status": UNAVAILABLE, "worst_ratio": None})
            elif row is None:
                cells.append({"status": "not run", "worst_ratio": None})
            else:
                r = row["worst_ratio"]
                cells.append({"status": row["status"] + (" (ref-only)" if row["reference_only"] else ""),
                              "worst_ratio": None if r is None else (r if r != float("inf") else "inf")})
        rows[cid] = {"title": clauses[cid].title if cid in clauses else "(undeclared)", "cells": cells}
    return {"schema": SCHEMA, "settings": settings.to_json(), "columns": columns, "clauses": rows}


def _cell(c: dict) -> str:
    r = c["worst_ratio"]
    if c["status"] in ("pass", "known", "fail") and r not in (None, 0.0):
        return f"{c['status']} {r if isinstance(r, str) else f'{r:.3g}'}"
    return c["status"]


def matrix_markdown(m: dict) -> str:
    """The matrix as a Markdown table (cells: status and worst error / tolerance), then one line
    per column on why it could not run, or what could not run in it."""
    cols = m["columns"]
    head = ["clause"] + [f"{c.get('name', column_slug(c['spec']))} {c.get('dtype', '')}".strip()
                         for c in cols]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cid, row in m["clauses"].items():
        lines.append("| " + " | ".join([cid] + [_cell(c) for c in row["cells"]]) + " |")
    notes = []
    for c in cols:
        why = c.get("load_error") or c.get("unavailable_reason")
        if why:
            notes.append(f"- `{c['spec']}`: {'not loaded' if c.get('load_error') else 'render n/a'}: {why}")
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def run_cli(a) -> int:
    """``python -m oracle matrix`` (oracle/__main__.py)."""
    from .runner import Settings

    if a.max_examples < 1:
        print(f"oracle: error: --max-examples: expected a positive integer, got {a.max_examples}",
              file=sys.stderr)
        return 2
    from .checks import cited_clauses
    from .clauses import expand_selection

    try:
        clauses = tuple(sorted(expand_selection(a.clause, cited_clauses()))) if a.clause else ()
    except ValueError as exc:
        print(f"oracle: error: {exc}", file=sys.stderr)
        return 2
    specs = tuple(a.backend) or DEFAULT_COLUMNS
    settings = Settings(max_examples=a.max_examples, seed=a.seed, shrink=not a.no_shrink,
                        clauses=clauses, timeout=a.timeout or None, memory_limit_mib=a.memory_limit)

    def progress(spec, what):
        print(f"  {spec:<60} {what}", file=sys.stderr, flush=True)

    m = build_matrix(specs, settings, a.report, progress)
    root = Path(a.report)
    atomic_write_json(root / "matrix.json", m)
    text = matrix_markdown(m)
    atomic_write_text(root / "matrix.md", text)
    print(text, end="")
    print(f"matrix: {root / 'matrix.md'} ({root / 'matrix.json'}); per column: {root}/<column>/index.html")
    return 0
