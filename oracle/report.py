"""Reports: the human-readable summary, the JSON report, reproducer files (ORC-07, ORC-06).

All files are written atomically (refgs/io/atomic.py: a temporary file in the same folder, then
``os.replace``).
The JSON schema is documented in docs/oracle.md ("The JSON report"); its ``schema`` field is
:data:`SCHEMA`.  Reproducers are ``.npz`` files of plain arrays and strings, loaded with
``allow_pickle=False``.  The page for a backend's author, index.html with its pictures, is
oracle/html.py (ORC-13).
"""
from __future__ import annotations

import io
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

import refgs
from refgs.io.atomic import atomic_write_bytes, atomic_write_text  # noqa: F401  (re-exported)

from .protocol import Case

SCHEMA = "refgs-oracle-report/2"
REPRO_FORMAT = "refgs-oracle-scene/1"
#: status precedence when several checks cite one clause, worst first (ORC-02, ORC-11)
STATUS_ORDER = ("crash", "timeout", "error", "fail", "known", "pass", "not provided", "n/a")


# ---------------------------------------------------------------------------------------------
# reproducers
# ---------------------------------------------------------------------------------------------


def save_case(path, scene: Case, **meta) -> Path:
    """Write ``scene`` and string/number ``meta`` (check, clauses, backend, ...) as an .npz."""
    g, c, cfg = scene.gaussians, scene.camera, scene.config
    arrays = {f: np.asarray(getattr(g, f), np.float64) for f in refgs.Gaussians.FIELDS}
    arrays.update(
        world_to_camera=np.asarray(c.world_to_camera, np.float64), K=np.asarray(c.K, np.float64),
        width=np.int64(c.width), height=np.int64(c.height), profile=np.str_(str(cfg.profile)),
        sh_degree=np.int64(-1 if cfg.sh_degree is None else cfg.sh_degree),
        background=np.asarray(cfg.background, np.float64), antialiased=np.bool_(cfg.antialiased),
        has_opacity_scale=np.bool_(cfg.opacity_scale is not None),
        opacity_scale=np.zeros(0) if cfg.opacity_scale is None else np.asarray(cfg.opacity_scale, np.float64),
        seed=np.int64(scene.seed), label=np.str_(scene.label), format=np.str_(REPRO_FORMAT))
    for k, v in meta.items():
        arrays[f"meta_{k}"] = np.str_(v) if isinstance(v, str) else np.asarray(v)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def load_case(path) -> tuple[Case, dict]:
    """Inverse of :func:`save_case`; ValueError naming the file if it is not a reproducer."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz reproducer ({exc})") from None
    if str(d.get("format", "")) != REPRO_FORMAT:
        raise ValueError(f"{path}: expected an oracle reproducer (format {REPRO_FORMAT}), "
                         f"got format {d.get('format')!r}")
    g = refgs.Gaussians(*(d[f] for f in refgs.Gaussians.FIELDS))
    cam = refgs.Camera(d["world_to_camera"], d["K"], int(d["width"]), int(d["height"]))
    deg = int(d["sh_degree"])
    cfg = refgs.RenderConfig(profile=str(d["profile"]), sh_degree=None if deg < 0 else deg,
                             background=tuple(float(x) for x in d["background"]),
                             antialiased=bool(d["antialiased"]),
                             opacity_scale=d["opacity_scale"] if bool(d["has_opacity_scale"]) else None)
    meta = {k[5:]: (str(v) if v.dtype.kind == "U" else v.tolist()) for k, v in d.items()
            if k.startswith("meta_")}
    return Case(g, cam, cfg, seed=int(d["seed"]), label=str(d["label"])), meta


# ---------------------------------------------------------------------------------------------
# clause table and summaries
# ---------------------------------------------------------------------------------------------


def machine() -> dict:
    """The machine and the versions of the numerical libraries a backend may use (None: absent;
    looked up without importing them)."""
    from importlib import metadata
    versions = {}
    for dist in ("scipy", "numba", "torch", "gsplat"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    return {"platform": platform.platform(), "python": sys.version.split()[0],
            "cpu_count": os.cpu_count(), "numpy": np.__version__, "machine": platform.machine(),
            **versions}


def clause_table(results, clauses: dict) -> dict:
    """Per clause: status (the worst of its checks' in :data:`STATUS_ORDER`), citing checks,
    worst ratio (ORC-02); a check's status for a clause is its ``clause_status`` override (a
    failure blamed on other clauses, ORC-12), else the check's status."""
    table: dict[str, dict] = {}
    for r in results:
        for cid in r.check.clauses:
            status = r.clause_status.get(cid, r.status)
            row = table.setdefault(cid, {"title": clauses[cid].title if cid in clauses else "(undeclared)",
                                         "status": "n/a", "checks": [], "worst_ratio": 0.0,
                                         "reference_only": True})
            row["checks"].append({"name": r.check.name, "status": status})
            if STATUS_ORDER.index(status) < STATUS_ORDER.index(row["status"]):
                row["status"] = status
            if status not in ("not provided", "n/a") and r.check.kind != "reference":
                row["reference_only"] = False
            if status == "pass" and r.status != "pass":   # spared by a failure: its passing examples
                ratio = None if r.worst is None else float(r.worst["ratio"])
            else:
                ratio = r.worst_ratio
            if ratio is not None and np.isfinite(ratio):
                row["worst_ratio"] = max(row["worst_ratio"], float(ratio))
            elif ratio is not None:
                row["worst_ratio"] = float("inf")
    for row in table.values():
        if row["status"] in ("not provided", "n/a"):
            row["reference_only"] = False
    return table


def to_json(run) -> dict:
    """The JSON report (schema in docs/oracle.md)."""
    be = run.backend
    table = clause_table(run.results, run.clauses)
    counts = {s: sum(1 for r in table.values() if r["status"] == s) for s in STATUS_ORDER}

    def ratio(x):
        return None if x is None else (x if np.isfinite(x) else "inf")

    return {
        "schema": SCHEMA,
        "backend": {"spec": be.spec, "name": be.name, "version": be.version, **be.capabilities()},
        "refgs": {"version": refgs.__version__, "spec_version": refgs.SPEC_VERSION},
        "oracle": {"version": run.oracle_version},
        "machine": machine(),
        "settings": run.settings.to_json(),
        "started": run.started, "duration_s": round(run.duration, 3),
        "exit_status": run.exit_status,
        "summary": counts,
        "check_summary": {s: sum(1 for r in run.results if r.status == s) for s in STATUS_ORDER},
        "clauses": {cid: {**row, "worst_ratio": ratio(row["worst_ratio"])} for cid, row in table.items()},
        "checks": [r.to_json() for r in run.results],
        "diagnosis": None if run.diagnosis is None else {
            k: run.diagnosis.get(k) for k in ("available", "summary", "deviations", "explained",
                                              "unexplained", "signatures")},
    }


def summary_text(run) -> str:
    """The human-readable report: header, one line per clause, then each failure in full."""
    be = run.backend
    table = clause_table(run.results, run.clauses)
    lines = [f"oracle: backend {be.spec or be.name} ({be.name} {be.version}), profile {be.profile}, {be.dtype}",
             f"reference refgs {refgs.__version__}, spec {refgs.SPEC_VERSION}; seed {run.settings.seed}, "
             f"max-examples {run.settings.max_examples}; {len(run.results)} checks in {run.duration:.1f} s",
             "", f"{'clause':<9}{'status':<16}{'worst/tol':>10}  checks"]
    from .clauses import clause_sort_key
    for cid in sorted(table, key=clause_sort_key):
        row = table[cid]
        st_ = row["status"] + (" (ref-only)" if row["reference_only"] else "")
        w = row["worst_ratio"]
        ws = "-" if row["status"] in ("n/a", "not provided") else ("inf" if not np.isfinite(w) else f"{w:.3g}")
        names = ", ".join(c["name"] + ("" if c["status"] == row["status"] else f" [{c['status']}]")
                          for c in row["checks"])
        lines.append(f"{cid:<9}{st_:<16}{ws:>10}  {names}")
    tied = [(r.check.name, max(t.get("max_pixels_in_band", 0) for k, t in r.ties.items() if isinstance(t, dict)),
             r.ties.get("flips", 0)) for r in run.results if any(isinstance(t, dict) for t in r.ties.values())]
    tied = [t for t in tied if t[1] or t[2]]
    if tied:
        lines += ["", "near-ties exempted (most pixels in one example / flips in all, ORC-04): " + ", ".join(
            f"{name} {n}/{f}" for name, n, f in tied)]
    unjudged = [r for r in run.results if r.inconclusive]
    if unjudged:
        lines += ["", "examples not judged (more near-ties than the budget, ORC-04): " + ", ".join(
            f"{r.check.name} {r.inconclusive} of {r.examples + r.inconclusive}" for r in unjudged)]
    known = [r for r in run.results if r.status == "known"]
    if known:
        lines += ["", "KNOWN DIFFERENCES (declared by the backend; not failures)"]
        for r in known:
            for e in r.known:
                lines.append(f"  {r.check.name} [{e.get('clause') or ', '.join(r.blame['blamed'])}]: "
                             f"{e['reason']}" + (f" ({e['link']})" if e.get("link") else ""))
    fails = [r for r in run.results if r.status not in ("pass", "n/a", "not provided", "known")]
    if fails:
        lines += ["", "FAILURES"]
        for r in fails:
            lines += failure_lines(r)
    if run.diagnosis is not None:
        dg = run.diagnosis
        lines += ["", "DIAGNOSIS (docs/spec/deviations.md DEV-02): " + dg["summary"]]
        for u in dg.get("unexplained", []):
            lines.append(f"  unexplained: {u['check']} ({u['status']}): {u['message'][:200]}")
        for u in dg.get("new_failures", []):
            lines.append(f"  new failure under the set: {u['check']}: {u['message'][:200]}")
    counts = {s: sum(1 for r in table.values() if r["status"] == s) for s in STATUS_ORDER}
    checks = {s: sum(1 for r in run.results if r.status == s) for s in STATUS_ORDER}
    lines += ["", "clauses: " + ", ".join(f"{counts[s]} {s}" for s in STATUS_ORDER if counts[s])
              + "; checks: " + ", ".join(f"{checks[s]} {s}" for s in STATUS_ORDER if checks[s])
              + f"  -> exit status {run.exit_status}"]
    return "\n".join(lines)


def failure_lines(r) -> list[str]:
    """The report's lines for one failing check result (``runner.CheckResult``): status, blamed
    clauses and message, the clauses spared, the smallest scene, the reproducer and its replay
    command."""
    f = r.failure or {"message": "(no details)"}
    blamed = ", ".join((r.blame or {}).get("blamed", {})) or (
        "no clause: unattributed" if (r.blame or {}).get("unattributed") else r.check.clauses[0])
    lines = [f"  {r.status.upper()} {r.check.name} [{blamed}]: {f['message']}"]
    if f.get("signature"):
        lines.append(f"    behaves like the reference with {f['signature']['label']} "
                     f"(the minimal case keeps this deviation signature)")
    spared = (r.blame or {}).get("spared", {})
    if spared:
        lines.append("    not blamed: " + "; ".join(f"{c} ({why})" for c, why in spared.items()))
    sc = f.get("scene")
    if sc is None:
        return lines
    lines.append(f"    smallest scene: N={sc['n_gaussians']}, {sc['width']}x{sc['height']} px, "
                 f"profile {sc['profile']}, sh_degree {sc['sh_degree']}, K={sc['sh_coeffs']}, "
                 f"background {sc['background']}, from {sc['label']!r}")
    lines += [f"      {line}" for line in f.get("parameters") or ()]
    if f.get("reproducer"):
        lines.append(f"    reproducer: {f['reproducer']}")
        lines.append(f"    replay: {f['replay']}")
    return lines


def scene_parameters(scene: Case, limit: int = 4) -> list[str]:
    """The Gaussians of a small scene, one line each (for the failure report)."""
    g = scene.gaussians
    if scene.n > limit:
        return []
    np.set_printoptions(precision=6, suppress=False)
    out = [f"camera K={np.asarray(scene.camera.K).round(6).tolist()}, "
           f"world_to_camera={np.asarray(scene.camera.world_to_camera).round(6).tolist()}"]
    for i in range(scene.n):
        out.append(f"g[{i}]: mean={g.means[i].tolist()}, log_scales={g.log_scales[i].tolist()}, "
                   f"quat={g.quats[i].tolist()}, logit={float(g.opacity_logits[i])}, "
                   f"sh0={g.sh[i, 0].tolist()}")
    return out


def write_report(run, folder) -> tuple[Path, Path]:
    """report.json and report.txt in ``folder`` (atomic); the page is oracle/html.py, and
    runner.write_reports writes all three."""
    folder = Path(folder)
    j = atomic_write_text(folder / "report.json", json.dumps(to_json(run), indent=2, sort_keys=False) + "\n")
    t = atomic_write_text(folder / "report.txt", summary_text(run) + "\n")
    return j, t
