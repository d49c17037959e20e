"""The report a backend's author reads: one static page, index.html, with pictures (ORC-13).

    write_page(run, "oracle-report")    # -> oracle-report/index.html, oracle-report/pictures/*.png

Self-contained: the CSS is inline, there is no script and nothing is fetched from the network;
the pictures (oracle/pictures.py) are PNG files in ``pictures/`` beside the page.  The page shows
the backend's identity and declared capabilities, a summary, then every check that did not pass
-- its status, the clauses it is blamed on and those it spares (ORC-12), the message, the smallest
case (one line per Gaussian when N <= 4), the tolerance applied with where it comes from, the
replay command and the pictures --, the declared known differences, the clause table (status,
worst error over tolerance, checks), and what was not run and why.
"""
from __future__ import annotations

from html import escape
from pathlib import Path

from refgs.io.atomic import atomic_write_text

from . import tolerances as tl
from .report import STATUS_ORDER, clause_table, machine
from .clauses import clause_sort_key
from .diagnosis_page import diagnosis_html
from .pictures import PICTURES

#: statuses that do not fail a run (runner.OK_STATUSES)
OK = ("pass", "n/a", "not provided", "known")
#: background colour of each status badge
COLOURS = {"crash": "#7b1fa2", "timeout": "#e65100", "error": "#c62828", "fail": "#d32f2f",
           "known": "#6d4c41", "pass": "#2e7d32", "not provided": "#757575", "n/a": "#9e9e9e"}

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:2em auto;max-width:72em;
     padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.5em;margin-bottom:.2em} h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #ddd;padding:.25em .5em;text-align:left;
     vertical-align:top} th{background:#f4f4f4}
.badge{display:inline-block;color:#fff;border-radius:.3em;padding:0 .45em;font-size:.85em;font-weight:600}
.verdict{font-size:1.1em;padding:.5em .8em;border-radius:.3em;color:#fff;display:inline-block}
article{border:1px solid #ddd;border-radius:.4em;padding:.2em 1em 1em;margin:1em 0;background:#fafafa}
pre{background:#f0f0f0;padding:.5em;overflow-x:auto;font-size:.85em;white-space:pre-wrap}
figure{display:inline-block;margin:.5em 1em .5em 0} figcaption{font-size:.8em;color:#555;max-width:40em}
img{max-width:100%;border:1px solid #ccc;background:#fff}
.muted{color:#666;font-size:.9em} .msg{font-family:monospace;font-size:.9em;white-space:pre-wrap}
.diag{border-left:.3em solid #1565c0;background:#e3f2fd;padding:.4em .8em}
"""


def badge(status: str) -> str:
    return f'<span class="badge" style="background:{COLOURS.get(status, "#444")}">{escape(status)}</span>'


def _kv_table(rows) -> str:
    return "<table>" + "".join(f"<tr><th>{escape(str(k))}</th><td>{escape(str(v))}</td></tr>"
                               for k, v in rows) + "</table>"


def tolerance_for(check, comparison: dict | None, dtype: str):
    """The tolerance row a failing comparison was judged by (None for a structural problem)."""
    if not comparison:
        return None
    out, ev = comparison.get("output", ""), comparison.get("evidence", "")
    name = out[1:] if ev == "backward" and out.startswith("d") else out
    name = name.replace("*|q|", "")
    stage = "backward" if ev == "backward" else (
        check.name[len("stage_"):] if ev == "stage" and check.name.startswith("stage_") else "render")
    try:
        return stage, name, tl.lookup(stage, name, dtype)
    except KeyError:
        return None


def _tolerance_html(check, comparisons, dtype: str) -> str:
    """One row per failing comparison: the tolerance it was judged by and where that comes from."""
    rows, sources = [], {}
    for c in comparisons:
        found = tolerance_for(check, c, dtype)
        if found is None:
            rows.append(f"<tr><td>{escape(c.get('output', ''))}</td><td colspan=\"4\">no tolerance: "
                        f"{escape(c.get('kind', 'value'))} (a structural problem, an exception, or a "
                        f"property that must hold exactly)</td></tr>")
            continue
        stage, name, t = found
        bound = "exact" if t.exact else (f"{t.atol:g}{' &times; row scale' if t.scaled else ''} + "
                                         f"{t.rtol:g} &times; |ref|")
        if isinstance(t, tl.GradTol):
            bound += (f"; rel L2 &le; {t.max_rel_l2:g}, cosine &ge; {t.min_cosine}, "
                      f"magnitude ratio &ge; {t.min_mag_ratio:g}")
        ref = sources.setdefault(t.measured_by, len(sources) + 1) if t.measured_by else None
        rows.append(f"<tr><td>{escape(c.get('output', ''))}</td><td>({stage}, {name}, {dtype})</td>"
                    f"<td>{bound}</td><td>{'-' if t.measured is None else f'{t.measured:.2g}'}"
                    f"{f' [{ref}]' if ref else ''}</td><td>{escape(t.rationale)}</td></tr>")
    notes = "".join(f"<li>[{i}] {escape(src)}</li>" for src, i in sources.items())
    return ("<p class=\"muted\">|got - ref| &le; atol' + rtol |ref| + the near-tie and conditioning "
            "allowances of ORC-04; rows are set by measurement with a 4x margin (ORC-03).</p>"
            "<table><tr><th>output</th><th>row</th><th>bound</th><th>measured</th><th>rationale</th></tr>"
            + "".join(rows) + "</table>" + (f"<ul class=\"muted\">{notes}</ul>" if notes else ""))


def _case_html(failure: dict) -> str:
    sc = failure.get("scene")
    if not sc:
        return '<p class="muted">No case: the check failed before any case could be judged.</p>'
    shrink = failure.get("shrink") or {}
    shrunk = ""
    if shrink:
        (n0, _), (s0, _) = shrink["gaussians"], shrink["image"]
        shrunk = (f" Shrunk from N={n0}, {s0[0]}x{s0[1]} px in {shrink['evaluations']} evaluations"
                  f" ({shrink.get('rejected_mechanism_changes', 0)} smaller cases rejected because the "
                  f"failure changed mechanism){'; ' + shrink['stopped'] if shrink.get('stopped') else ''}.")
    head = (f"<p>N={sc['n_gaussians']}, {sc['width']}x{sc['height']} px, profile {escape(sc['profile'])}, "
            f"SH degree {sc['sh_degree']} with K={sc['sh_coeffs']}, background {sc['background']}, "
            f"opacity_scale {'yes' if sc['opacity_scale'] else 'no'}, from "
            f"<code>{escape(sc['label'])}</code>.{escape(shrunk)}</p>")
    params = failure.get("parameters") or []
    return head + (f"<pre>{escape(chr(10).join(params))}</pre>" if params else "")


def _failure_html(r, run, folder: Path) -> str:
    from .pictures import draw
    f = r.failure or {"message": "(no details)"}
    blame = r.blame or {}
    blamed = "".join(f"<li><b>{escape(c)}</b>: {escape(why)}</li>" for c, why in blame.get("blamed", {}).items())
    spared = "".join(f"<li>{escape(c)}: {escape(why)}</li>" for c, why in blame.get("spared", {}).items())
    parts = [f'<article id="check-{escape(r.check.name)}">',
             f"<h3>{badge(r.status)} <code>{escape(r.check.name)}</code> "
             f"<span class=\"muted\">({escape(r.check.kind)}; cites {escape(', '.join(r.check.clauses))})</span></h3>",
             f"<p class=\"muted\">{escape(r.check.doc)}</p>", f"<p class=\"msg\">{escape(f['message'])}</p>"]
    sig = f.get("signature")
    if sig:
        parts.append(f'<p class="diag">Behaves like the reference with <b>{escape(sig["label"])}</b> '
                     "(the diagnosis, docs/spec/deviations.md DEV-02; the minimal case below was shrunk "
                     "keeping this deviation signature).</p>")
    if r.known:
        parts.append("<p>Known difference: " + "; ".join(
            escape(e["reason"]) + (f' (<a href="{escape(e["link"])}">{escape(e["link"])}</a>)' if e.get("link") else "")
            for e in r.known) + "</p>")
    if blamed:
        parts.append(f"<p>Blamed clauses (ORC-12):</p><ul>{blamed}</ul>")
    elif blame.get("unattributed"):
        parts.append(f"<p>Blamed clauses (ORC-12): none -- {escape(blame['unattributed'])}.</p>")
    if spared:
        parts.append(f"<details><summary>Clauses this failure is not evidence against</summary><ul>{spared}</ul></details>")
    note = {"crash": "the worker died on this case (see the message)",
            "timeout": "the backend ran out of time on this case"}.get(r.status, "")
    try:
        pics = draw(r.evidence, folder / PICTURES, r.check.name, note=note)
    except Exception as exc:                         # a picture must never cost the report
        pics = []
        parts.append(f'<p class="muted">The pictures could not be drawn: {escape(type(exc).__name__)}: '
                     f"{escape(str(exc))}</p>")
    if pics:
        parts.append("<h4>The smallest failing case, drawn</h4>")
        parts += [f'<figure><img src="{PICTURES}/{escape(name)}" alt="{escape(r.check.name)}: {escape(cap)}">'
                  f"<figcaption>{escape(cap)}</figcaption></figure>" for name, cap in pics]
    parts += ["<h4>" + ("The case it was on" if r.status in ("crash", "timeout") else "Smallest failing case")
              + "</h4>", _case_html(f)]
    if f.get("replay"):
        parts.append(f"<p>Replay (prints the comparison and redraws these pictures):</p><pre>{escape(f['replay'])}</pre>")
    if r.status in ("fail", "error", "known"):
        verdict = (r.evidence or {}).get("verdict")
        bad = ([c.to_json() for c in verdict.comparisons if not c.ok] if verdict is not None
               else [f["comparison"]] if f.get("comparison") else [])
        parts += ["<h4>Tolerance applied</h4>", _tolerance_html(r.check, bad, run.backend.dtype)]
    parts.append("</article>")
    return "\n".join(parts)


def render_page(run, folder) -> str:
    """The page's HTML (drawing the pictures into ``folder``/pictures)."""
    folder = Path(folder)
    be = run.backend
    table = clause_table(run.results, run.clauses)
    failing = [r for r in run.results if r.status not in OK]
    known = [r for r in run.results if r.status == "known"]
    skipped = [r for r in run.results if r.status in ("n/a", "not provided")]
    checks = {s: sum(1 for r in run.results if r.status == s) for s in STATUS_ORDER}
    ok = run.exit_status == 0
    title = f"oracle report: {be.name}"
    caps = be.capabilities()
    verdict = ("every check passed or is n/a, not provided or a declared known difference" if ok else
               f"{len(failing)} of {len(run.results)} checks did not pass")
    body = [f"<h1>{escape(title)}</h1>",
            f"<p><code>{escape(be.spec or be.name)}</code> ({escape(be.name)} {escape(be.version)}), "
            f"profile {escape(be.profile)}, {escape(be.dtype)}; judged against refgs "
            f"{escape(str(__import__('refgs').__version__))} at float64.</p>",
            f'<p class="verdict" style="background:{COLOURS["pass" if ok else "fail"]}">'
            f"exit status {run.exit_status}: {escape(verdict)}</p>",
            "<p>" + " ".join(f"{badge(s)}&nbsp;{checks[s]}" for s in STATUS_ORDER if checks[s])
            + f" of {len(run.results)} checks; {run.settings.max_examples} examples per check, seed "
              f"{run.settings.seed}, {run.duration:.1f} s.</p>"]
    if run.diagnosis is not None:
        body.append(diagnosis_html(run.diagnosis))
    if failing:
        body.append("<h2>Checks that did not pass</h2>")
        body += [_failure_html(r, run, folder) for r in failing]
    if known:
        body.append("<h2>Known differences</h2>")
        body += [_failure_html(r, run, folder) for r in known]
    rows = []
    for cid in sorted(table, key=clause_sort_key):
        row = table[cid]
        w = row["worst_ratio"]
        ws = "-" if row["status"] in ("n/a", "not provided") else ("inf" if w == float("inf") else f"{w:.3g}")
        names = ", ".join((f'<a href="#check-{escape(c["name"])}">{escape(c["name"])}</a>'
                           if c["status"] not in OK + ("pass",) or any(r.check.name == c["name"] for r in failing + known)
                           else escape(c["name"])) + ("" if c["status"] == row["status"] else f" [{escape(c['status'])}]")
                          for c in row["checks"])
        rows.append(f"<tr id=\"clause-{escape(cid)}\"><td>{escape(cid)}</td><td>{escape(row['title'])}</td><td>{badge(row['status'])}"
                    f"{' (reference only)' if row['reference_only'] else ''}</td><td>{ws}</td><td>{names}</td></tr>")
    body += ["<h2>Clauses</h2>", "<p class=\"muted\">Status: the worst of the checks citing the clause; a "
             "failure counts only against the clauses it is evidence against (ORC-12). Worst/tol: the "
             "largest error over its tolerance in passing examples.</p>",
             "<table><tr><th>clause</th><th>title</th><th>status</th><th>worst/tol</th><th>checks</th></tr>"
             + "".join(rows) + "</table>"]
    body += ["<h2>Backend and declared capabilities</h2>",
             _kv_table([("spec", be.spec), ("name", be.name), ("version", be.version)]
                       + [(k, ", ".join(v) if isinstance(v, list) else v) for k, v in caps.items()])]
    if skipped:
        body += ["<h2>Not run</h2><table><tr><th>check</th><th>status</th><th>why</th></tr>"
                 + "".join(f"<tr><td><code>{escape(r.check.name)}</code></td><td>{badge(r.status)}</td>"
                           f"<td>{escape(r.reason)}</td></tr>" for r in skipped) + "</table>"]
    m = machine()
    body.append(f'<p class="muted">refgs {escape(str(__import__("refgs").__version__))}, oracle '
                f"{escape(run.oracle_version)}; started {escape(run.started)}; {escape(str(m['platform']))}, "
                f"Python {escape(str(m['python']))}, {m['cpu_count']} CPUs. Files: report.json, report.txt.</p>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{escape(title)}</title><style>{CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")


def write_page(run, folder) -> Path:
    """Write ``folder``/index.html and its pictures (atomic); returns the page's path."""
    folder = Path(folder)
    return atomic_write_text(folder / "index.html", render_page(run, folder))


def write_diagnosis_page(result: dict, folder) -> Path:
    """``folder``/diagnosis.html: the diagnosis of ``python -m oracle diagnose`` (a result of
    oracle/diagnose.py ``diagnose``) as a page of its own, pictures in ``pictures/``."""
    b = result["backend"]
    title = f"oracle diagnosis: {b['spec'] or b['name']}"
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{escape(title)}</title><style>{CSS}</style></head><body>\n"
            f"<h1>{escape(title)}</h1><p>{escape(b['name'])} {escape(str(b['version']))}, profile "
            f"{escape(b['profile'])}, {escape(b['dtype'])}; {result['duration_s']} s.</p>\n"
            + diagnosis_html(result) + "\n</body></html>\n")
    return atomic_write_text(Path(folder) / "diagnosis.html", page)
