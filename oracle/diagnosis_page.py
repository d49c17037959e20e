"""The diagnosis as HTML (DEV-02, DEV-03): a section of index.html and, for ``python -m oracle
diagnose --report DIR``, of a page of its own, ``diagnosis.html`` (both written by oracle/html.py).

In this order, so that the author of a renderer that differs in many ways learns first where it
differs: the stage probes' verdicts with their pictures (expected | got | difference, without
deviations); the named set and what it explains; what is left, by stage, each with its sentence
and the probe's picture under the set; then checks left unexplained, new failures and what was not
diagnosed.  Pictures are PNG files in ``pictures/`` beside the page (drawn by the diagnosis,
oracle/diagnose.py ``pictures=``).
"""
from __future__ import annotations

from html import escape

from .pictures import PICTURES

#: status colours of the stage probes' verdicts
VERDICT_COLOURS = {"agree": "#2e7d32", "differ": "#d32f2f", "inconclusive": "#757575"}


def _verdict(st: str) -> str:
    return (f'<span class="badge" style="background:{VERDICT_COLOURS.get(st, "#757575")}">'
            f"{escape(st)}</span>")


def _img(name: str | None, alt: str) -> str:
    if not name:
        return '<span class="muted">no picture</span>'
    return (f'<a href="{PICTURES}/{escape(name)}"><img src="{PICTURES}/{escape(name)}" '
            f'alt="{escape(alt)}" style="max-width:24em"></a>')


def stage_probes_html(rows: list[dict]) -> str:
    """The stage probes' table: verdict without deviations and under the set, with pictures."""
    if not rows:
        return ('<p class="muted">No stage probes: the backend\'s render cannot run here (its stage '
                'functions were judged instead).</p>')
    body = "".join(
        f"<tr><td><code>{escape(r['name'])}</code></td><td>{escape(r['stage'])}</td>"
        f"<td>{escape(', '.join(r['clauses']))}</td><td>{escape(r['adds'])}</td>"
        f"<td>{_verdict(r['before'])} {r['distance_before']:.2f}</td>"
        f"<td>{_verdict(r['status'])} {r['distance']:.2f}</td>"
        f"<td>{_img(r.get('picture'), 'stage probe ' + r['name'] + ': expected, got, difference')}</td></tr>"
        for r in rows)
    return ("<p class=\"muted\">Small scenes that let one mechanism differ at a time "
            "(oracle/stage_probes.py); each extends the probe named in its ladder by what the "
            "fourth column says. Distance: summed log10(1 + error / tolerance) over the outputs "
            "that differ; pictures: the reference without deviations, the backend, |difference| "
            "(image and alpha).</p><table><tr><th>probe</th><th>stage</th><th>clauses</th>"
            "<th>what it adds</th><th>without deviations</th><th>under the set</th><th>picture</th></tr>"
            + body + "</table>")


def named_set_html(d: dict, explained_checks) -> str:
    """The named set with citations, and what it explains."""
    parts = []
    if d.get("details"):
        parts.append("<ul>" + "".join(
            f"<li><code>{escape(x['name'])}</code> ({escape(x['stage'])}, {escape(x['clause'])}): "
            f"{escape(x['label'])} -- <span class=\"muted\">{escape(x['who'])}</span></li>"
            for x in d["details"]) + "</ul>")
    else:
        parts.append("<p>No catalogued deviation brings the reference closer to the backend.</p>")
    sp = d.get("stage_probes", [])
    w = d["witnesses"]
    s = d["search"]
    parts.append(f"<p>Explains {sum(r['explained'] for r in sp)} of "
                 f"{sum(r['before'] == 'differ' for r in sp)} differing stage probes and "
                 f"{len(w['explained'])} of {len(w['differing'])} differing witnesses; the summed "
                 f"distance falls from {s['distance_before']} to {s['distance_after']} over "
                 f"{s['probes']} probes.</p>")
    if explained_checks:
        parts.append("<p>Explained checks: " + ", ".join(
            f'<a href="#check-{escape(c)}">{escape(c)}</a>' for c in explained_checks) + "</p>")
    if s.get("trace"):
        parts.append("<details><summary>The search, move by move</summary><ol>" + "".join(
            f"<li>{escape(t['move'])}: +{escape(', '.join(t['added']) or '-')}, "
            f"-{escape(', '.join(t['dropped']) or '-')}; gain {t['gain']}, distance {t['distance']}</li>"
            for t in s["trace"]) + "</ol></details>")
    return "".join(parts)


def residual_html(d: dict) -> str:
    """What is left under the set, by stage, with the probes' pictures under the set."""
    res = d.get("residual") or {}
    if not res:
        return ""
    pics = {r["name"]: r.get("residual_picture") for r in d.get("stage_probes", [])}
    parts = [f"<p><b>{escape(res['summary'])}</b>.</p>"]
    for stage in res.get("stages", []):
        parts.append(f"<h4>{escape(stage)}</h4><ul>")
        for e in res["by_stage"][stage]:
            pic = pics.get(e["probe"])
            parts.append(f"<li>{escape(e['sentence'])}"
                         + (f"<br>{_img(pic, e['probe'] + ' under the set: expected, got, difference')}"
                            if pic else "") + "</li>")
        parts.append("</ul>")
    left = res.get("unlocalised") or res.get("also_differing") or []
    if left:
        parts.append("<p>Checks whose scenes still differ under the set"
                     + (" and that no stage probe places" if res.get("unlocalised") else "")
                     + ": " + ", ".join(escape(c) for c in left) + "</p>")
    return "".join(parts)


def diagnosis_html(dg: dict) -> str:
    """The diagnosis section: ``dg`` is a run's diagnosis block (oracle/triage.py, its full
    result under ``diagnosis``) or a result of oracle/diagnose.py ``diagnose``."""
    if not dg.get("available", True):
        return f'<div class="diag"><p>{escape(dg["summary"])}</p></div>'
    d = dg.get("diagnosis") or dg
    if "witnesses" not in d:                         # a run with nothing to diagnose
        return f'<div class="diag"><p><b>Diagnosis</b>: {escape(dg["summary"])}.</p></div>'
    ver = d.get("verification") or {}
    explained = dg.get("explained") if "explained" in dg and "diagnosis" in dg else ver.get("explained", [])
    unexplained = dg.get("unexplained") if "diagnosis" in dg else ver.get("unexplained", [])
    parts = [f'<div class="diag"><h2>Diagnosis</h2><p>(docs/spec/deviations.md DEV-02, DEV-03) '
             f'{escape(dg["summary"])}.</p>',
             "<h3>Stage probes</h3>", stage_probes_html(d.get("stage_probes", [])),
             "<h3>The named set and what it explains</h3>", named_set_html(d, explained),
             "<h3>What is left, by stage</h3>", residual_html(d)]
    if unexplained:
        parts.append("<p>Checks left unexplained (a defect, or a convention the catalogue does not "
                     "name):</p><ul>" + "".join(
                         f'<li><a href="#check-{escape(u["check"])}">{escape(u["check"])}</a>: '
                         f'<span class="msg">{escape(u["message"][:300])}</span></li>' for u in unexplained)
                     + "</ul>")
    new = dg.get("new_failures") if "diagnosis" in dg else ver.get("new_failures", [])
    if new:
        parts.append("<p>New failures under the set:</p><ul>" + "".join(
            f"<li>{escape(u['check'])}: {escape(u['message'][:300])}</li>" for u in new) + "</ul>")
    nd = dg.get("not_diagnosed") or []
    if nd:
        parts.append("<p>Not diagnosed: " + ", ".join(
            f"{escape(u['check'])} ({escape(u.get('status') or u.get('kind', ''))})" for u in nd) + "</p>")
    parts.append(f'<p class="muted">Full result: diagnosis.json ({dg.get("duration_s", 0):.1f} s).</p></div>')
    return "".join(parts)


__all__ = ["diagnosis_html", "named_set_html", "residual_html", "stage_probes_html"]
