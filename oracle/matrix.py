"""The conformance matrix: one column per backend, one row per clause (docs/conformance.md).

    python -m oracle matrix [--backend SPEC ...] [--clause ID ...] [--max-examples N] [--seed S]
                            [--report DIR] [--no-shrink] [--no-diagnose] [--timeout S]
                            [--memory-limit MIB]

Each backend runs in its own worker process (oracle/runner.py ``run_isolated``) with the same
settings; its failing checks are then diagnosed through the same worker (oracle/triage.py
``run_diagnosed``:
which named deviations explain them), and its full report -- report.json, report.txt,
diagnosis.json, index.html with its pictures, failures/*.npz -- goes to ``DIR/<column>/``
(runner.write_reports).  A backend that cannot be loaded here (a package not installed) is a
column of ``unavailable`` cells with the one-line reason; a column that needs a GPU is a column
of ``n/a: no GPU here`` cells on a machine without one (it is not run).  The matrix is a
measurement: the command exits 0 once ``matrix.json``, ``matrix.md`` and ``matrix.html`` are
written, 2 on a usage error; each column records its own ``check`` exit status.

    matrix.json   {"schema", "settings", "gpu", "columns": [{spec, title, gpu, name, version,
                  profile, dtype, unavailable_reason, load_error, not_run, exit_status, report,
                  page, summary, check_summary, duration_s, diagnosis}],
                  "clauses": {id: {title, cells: [{status, worst_ratio, why}]}}}
    matrix.html   the table; each cell links to its column's index.html at the clause's row
"""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from dataclasses import dataclass, replace
from html import escape
from pathlib import Path

from refgs.io.atomic import atomic_write_json, atomic_write_text

from .clauses import clause_sort_key, load_clauses
from .protocol import BackendError
from .report import STATUS_ORDER, clause_table

SCHEMA = "refgs-oracle-matrix/2"
#: a cell of a backend that could not be loaded
UNAVAILABLE = "unavailable"
#: why a GPU column is not run on a machine without a CUDA device
NO_GPU = "no GPU here"
#: seconds the CUDA probe (a python process importing torch) may take
GPU_PROBE_TIMEOUT_S = 120


@dataclass(frozen=True)
class Column:
    """One column: the backend's ``module:object`` spec (or registry name), its title, and
    whether it needs a CUDA device (``gpu``: n/a without one, not run)."""

    spec: str
    title: str = ""
    gpu: bool = False

    @property
    def label(self) -> str:
        return self.title or column_slug(self.spec)


_A = "oracle.adapters."
#: the columns of ``python -m oracle matrix`` without --backend (docs/conformance.md)
DEFAULT_COLUMNS = (
    Column(_A + "refgs_backend:refgs_float32", "refgs float32"),
    Column(_A + "refgs_backend:refgs_gsplat_float32", "refgs gsplat float32"),
    Column("refgs.fast:fast_float32", "refgs.fast float32"),
    Column("refgs.fast:fast_float64", "refgs.fast float64"),
    Column("refgs.fast:fast_gsplat_float32", "refgs.fast gsplat float32"),
    Column("refgs.fast:fast_float32_geom64", "refgs.fast float32, float64 geometry"),
    Column(_A + "torch_backend:torch_float32", "torch transcription float32"),
    Column(_A + "gsplat_backend:gsplat_cpu", "gsplat 1.5.3 CPU functions"),
    Column(_A + "gsplat_backend:gsplat_cuda", "gsplat 1.5.3 CUDA", gpu=True),
    Column(_A + "gswarp_backend:gswarp_cpu", "gswarp 1.1.0 CPU (Warp)"),
    Column(_A + "gswarp_backend:gswarp_cuda", "gswarp 1.1.0 CUDA", gpu=True),
    Column(_A + "taichi_splatting_backend:taichi_float32", "taichi-splatting 0.13.0 float32 CPU"),
    Column(_A + "taichi_splatting_backend:taichi_float64", "taichi-splatting 0.13.0 float64 CPU"),
    Column(_A + "taichi_splatting_backend:taichi_cuda32", "taichi-splatting 0.13.0 CUDA float32",
           gpu=True),
)


def column_slug(spec: str) -> str:
    """A folder name for ``spec``: its object name, else the module's last part."""
    mod, _, obj = spec.partition(":")
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", obj or mod.rsplit(".", 1)[-1]) or "backend"


def cuda_available() -> bool:
    """Whether a CUDA device is usable here: an NVIDIA device node, and torch (in a separate
    process: the oracle never imports a backend's libraries) sees a device."""
    if not any(Path("/dev").glob("nvidia[0-9]*")) or importlib.util.find_spec("torch") is None:
        return False
    try:
        r = subprocess.run([sys.executable, "-c", "import sys, torch; "
                            "sys.exit(0 if torch.cuda.is_available() else 1)"],
                           capture_output=True, timeout=GPU_PROBE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


def _diagnosis_block(dg: dict | None) -> dict | None:
    if dg is None:
        return None
    return {"available": dg.get("available", True), "summary": dg["summary"],
            "deviations": dg.get("deviations", []),
            "labels": [d["label"] for d in dg.get("details", [])],
            "explained": dg.get("explained", []),
            "unexplained": [u["check"] for u in dg.get("unexplained", [])]}


def run_column(col: Column, settings, root: Path, gpu: bool, diagnose: bool):
    """Run one column (module docstring): (column record, clause table or None)."""
    from .runner import run_isolated, write_reports
    from .triage import run_diagnosed

    slug = column_slug(col.spec)
    rec = {"spec": col.spec, "title": col.label, "gpu": col.gpu, "load_error": None,
           "not_run": None, "exit_status": None, "report": None, "page": None, "diagnosis": None}
    if col.gpu and not gpu:
        rec["not_run"] = NO_GPU
        return rec, None
    folder = root / slug
    try:
        runner = run_diagnosed if diagnose else run_isolated
        result = runner(col.spec, replace(settings, report_dir=str(folder)))
    except BackendError as exc:
        rec["load_error"] = str(exc)
        return rec, None
    write_reports(result, folder)
    be = result.backend
    table = clause_table(result.results, result.clauses)
    rec.update(name=be.name, version=be.version, profile=be.profile, dtype=be.dtype,
               unavailable_reason=be.unavailable_reason, exit_status=result.exit_status,
               report=slug, page=f"{slug}/index.html", duration_s=round(result.duration, 1),
               summary={s: sum(1 for r in table.values() if r["status"] == s) for s in STATUS_ORDER},
               check_summary={s: sum(1 for r in result.results if r.status == s) for s in STATUS_ORDER},
               diagnosis=_diagnosis_block(result.diagnosis))
    return rec, table


def build_matrix(columns, settings, report_dir, progress=None, gpu: bool | None = None,
                 diagnose: bool = True) -> dict:
    """Run every column (Column, or a spec string) with ``settings`` (oracle/runner.py
    ``Settings``; its report_dir is replaced per column) and return the matrix dict (module
    docstring); writes each column's report.  ``gpu``: whether GPU columns run (None: detect)."""
    columns = [c if isinstance(c, Column) else Column(c) for c in columns]
    gpu = cuda_available() if gpu is None and any(c.gpu for c in columns) else bool(gpu)
    root = Path(report_dir)
    clauses = load_clauses()
    recs, tables = [], []
    for col in columns:
        rec, table = run_column(col, settings, root, gpu, diagnose)
        recs.append(rec)
        tables.append(table)
        if progress is not None:
            progress(col.spec, f"n/a: {rec['not_run']}" if rec["not_run"] else
                     f"{UNAVAILABLE}: {rec['load_error']}" if rec["load_error"] else
                     f"exit {rec['exit_status']} in {rec['duration_s']} s")
    ids = sorted({cid for t in tables if t for cid in t}, key=clause_sort_key)
    rows = {}
    for cid in ids:
        cells = []
        for rec, t in zip(recs, tables):
            row = None if t is None else t.get(cid)
            if rec["not_run"]:
                cells.append({"status": "n/a", "worst_ratio": None, "why": rec["not_run"]})
            elif t is None:
                cells.append({"status": UNAVAILABLE, "worst_ratio": None, "why": rec["load_error"]})
            elif row is None:
                cells.append({"status": "not run", "worst_ratio": None, "why": "no check selected"})
            else:
                r = row["worst_ratio"]
                cells.append({"status": row["status"] + (" (ref-only)" if row["reference_only"] else ""),
                              "worst_ratio": None if r is None else (r if r != float("inf") else "inf"),
                              "why": None})
        rows[cid] = {"title": clauses[cid].title if cid in clauses else "(undeclared)", "cells": cells}
    return {"schema": SCHEMA, "settings": settings.to_json(), "gpu": gpu, "columns": recs, "clauses": rows}


def cell_text(c: dict) -> str:
    """A cell as text: status and worst error / tolerance, or why it was not run."""
    r = c["worst_ratio"]
    if c.get("why") and c["status"] in ("n/a", UNAVAILABLE):
        return f"{c['status']}: {c['why']}" if c["why"] == NO_GPU else c["status"]
    if c["status"].split(" ")[0] in ("pass", "known", "fail", "error") and r not in (None, 0.0):
        return f"{c['status']} {r if isinstance(r, str) else f'{r:.3g}'}"
    return c["status"]


def _deviation_cell(rec: dict) -> str:
    dg = rec.get("diagnosis")
    if dg is None:
        return "-"
    if not dg["available"]:
        return "not available"
    return ", ".join(dg["deviations"]) or ("none needed" if not dg["unexplained"] else "none found")


def matrix_markdown(m: dict) -> str:
    """The matrix as a Markdown table (cells: status and worst error / tolerance), a row of the
    deviations each column's diagnosis found, then one line per column on its diagnosis and on
    what could not run."""
    cols = m["columns"]
    lines = ["| clause | " + " | ".join(c["title"] for c in cols) + " |", "|" + "---|" * (len(cols) + 1)]
    for cid, row in m["clauses"].items():
        lines.append("| " + " | ".join([cid] + [cell_text(c) for c in row["cells"]]) + " |")
    lines.append("| deviations (diagnosis) | " + " | ".join(_deviation_cell(c) for c in cols) + " |")
    notes = []
    for c in cols:
        dg = c.get("diagnosis")
        if dg is not None and (dg["deviations"] or dg["unexplained"] or not dg["available"]):
            extra = f"; unexplained: {', '.join(dg['unexplained'])}" if dg["unexplained"] else ""
            notes.append(f"- {c['title']}: {dg['summary']}{extra}")
    for c in cols:
        why = c.get("load_error") or c.get("unavailable_reason")
        if c.get("not_run"):
            notes.append(f"- {c['title']} (`{c['spec']}`): not run: {c['not_run']}")
        elif why:
            notes.append(f"- {c['title']} (`{c['spec']}`): "
                         f"{'not loaded' if c.get('load_error') else 'render n/a'}: {why}")
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def matrix_html(m: dict) -> str:
    """The matrix as one static page; each cell links to its column's index.html at the row of
    the clause, each column title to the page itself."""
    from .html import COLOURS, CSS

    cols = m["columns"]

    def head(c):
        t = escape(c["title"])
        return f'<th><a href="{escape(c["page"])}">{t}</a></th>' if c.get("page") else f"<th>{t}</th>"

    def cell(c, rec, cid):
        text = escape(cell_text(c))
        colour = COLOURS.get(c["status"].split(" ")[0], "#bdbdbd")
        inner = (f'<a style="color:#fff" href="{escape(rec["page"])}#clause-{escape(cid)}">{text}</a>'
                 if rec.get("page") else text)
        return f'<td style="background:{colour};color:#fff">{inner}</td>'

    rows = [f"<tr><td><b>{escape(cid)}</b><br><span class=\"muted\">{escape(row['title'])}</span></td>"
            + "".join(cell(c, rec, cid) for c, rec in zip(row["cells"], cols)) + "</tr>"
            for cid, row in m["clauses"].items()]
    rows.append("<tr><td><b>deviations</b><br><span class=\"muted\">the diagnosis (DEV-02)</span></td>"
                + "".join(f"<td>{escape(_deviation_cell(c))}</td>" for c in cols) + "</tr>")
    notes = "".join(f"<li>{escape(line[2:])}</li>" for line in matrix_markdown(m).split("\n")
                    if line.startswith("- "))
    s = m["settings"]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>oracle conformance "
            f"matrix</title><style>{CSS}body{{max-width:none}}</style></head><body>\n"
            "<h1>Conformance matrix</h1><p>One column per backend, one row per clause: the status "
            "and the worst error over its tolerance (docs/conformance.md). "
            f"{s['max_examples']} examples per check, seed {s['seed']}; GPU here: "
            f"{'yes' if m['gpu'] else 'no'}. Each cell links to the column's report.</p>\n"
            "<table><tr><th>clause</th>" + "".join(head(c) for c in cols) + "</tr>"
            + "".join(rows) + "</table>\n" + (f"<ul>{notes}</ul>" if notes else "") + "</body></html>\n")


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
    columns = tuple(Column(s) for s in a.backend) or DEFAULT_COLUMNS
    settings = Settings(max_examples=a.max_examples, seed=a.seed, shrink=not a.no_shrink,
                        clauses=clauses, timeout=a.timeout or None, memory_limit_mib=a.memory_limit)

    def progress(spec, what):
        print(f"  {spec:<60} {what}", file=sys.stderr, flush=True)

    m = build_matrix(columns, settings, a.report, progress, diagnose=not a.no_diagnose)
    root = Path(a.report)
    atomic_write_json(root / "matrix.json", m)
    text = matrix_markdown(m)
    atomic_write_text(root / "matrix.md", text)
    atomic_write_text(root / "matrix.html", matrix_html(m))
    print(text, end="")
    print(f"matrix: {root / 'matrix.html'} ({root / 'matrix.md'}, {root / 'matrix.json'}); "
          f"per column: {root}/<column>/index.html")
    return 0


__all__ = ["Column", "DEFAULT_COLUMNS", "NO_GPU", "SCHEMA", "build_matrix", "cell_text",
           "column_slug", "cuda_available", "matrix_html", "matrix_markdown", "run_column"]
