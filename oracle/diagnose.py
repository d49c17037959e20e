"""Which named deviations explain a backend's failures, and what is left (docs/spec/deviations.md,
DEV-02, DEV-03).

    result = diagnose("oracle.meta.deviant:gsplat_as_inria")     # a spec, BackendInfo or object
    result["summary"]   # "behaves like the reference with {...}: explains 9 of 9 failing checks,
                        #  0 new failures"
    result["residual"]  # where the outputs first part under that set (oracle/residual.py)

One scene at a time: the backend's output against the float64 reference rendered with a set of
deviations on (``RenderConfig.deviations``), judged by the checks' own comparisons and the
tolerance table (oracle/explain.py, oracle/evaluate.py, oracle/tolerances.py).  The backend's
outputs are memoised per scene (only the reference changes while the search runs); given a
BackendInfo of an isolated worker (oracle/isolation.py ``open_backend``, what ``python -m oracle
diagnose`` and ``check --diagnose`` use) the backend runs there, so a backend that crashes or
hangs costs the scene it was on, not the diagnosis.  Steps:

1. probes -- the stage probes (oracle/stage_probes.py: one mechanism each), the witness scene of
   every deviation (refgs/deviations.py; for a backend whose render cannot run here, judged
   through its stage functions), scenes of every render-level and stage check (the first
   failing one also shrunk, oracle/shrink.py) and the failing scenes of a check run (``extra``);
2. the search (oracle/search.py): stepwise selection by the distance left on every probe, first
   over the small scenes, then over all of them from that set;
3. what is left (oracle/residual.py): per probe, the distance under the set; the stage where the
   outputs first part, from the stage probes' ladder and the backend's stage functions;
4. verification on fresh scenes of the checks.  A failure no set explains is reported as
   unexplained, with its stage where one is found, never guessed.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from hypothesis import HealthCheck, Phase, Verbosity, given
from hypothesis import seed as hseed
from hypothesis import settings as hsettings

import refgs
from refgs.deviations import DEVIATIONS, apply_deviations, label
from refgs.io.atomic import atomic_write_json, atomic_write_text

from .checks import CHECKS, Check
from .compare import problem
from .evaluate import Context, Verdict
from .explain import (Probe, backend_info, explains, fingerprint, judge, plain_context,
                      with_deviations)
from .pictures import PICTURES
from .protocol import BackendError, BackendInfo, Case
from .residual import STAGE_OF_FUNCTION, draw_probe, localise
from .residual import summary as residual_summary
from .search import DistanceSearch
from .shrink import shrink
from .stage_probes import STAGE_PROBES, stage_probe_cases

#: check kinds judged by comparison with the reference, hence explainable by a deviation
DIAGNOSED_KINDS = ("forward", "backward", "hard", "stage")
#: scenes drawn per check in the first pass and in the verification (times Check.examples)
DEFAULT_EXAMPLES = 6
#: failing scenes of one check kept as probes (the first is also shrunk)
KEEP_FAILING = 1
#: check evaluations one shrink may spend
SHRINK_BUDGET = 20
#: scenes drawn per passing check to look for new failures in the verification (and per check
#: outside ``focus`` in the first pass)
PASSING_SAMPLE = 2


def _draw(check: Check, ctx: Context, n: int, seed: int) -> list[Case]:
    """Up to ``n`` scenes of the check's strategy (hypothesis, seeded, no database), rounded."""
    scenes: list = []

    def collect(scene):
        scenes.append(scene)

    test = given(scene=check.scenes(ctx))(collect)
    test = hsettings(max_examples=max(1, n), deadline=None, database=None, phases=[Phase.generate],
                     suppress_health_check=list(HealthCheck), verbosity=Verbosity.quiet)(test)
    hseed(seed)(test)()
    return [s.rounded(ctx.dtype) for s in scenes[:max(1, n)]]


def _stage_checks(info: BackendInfo) -> list[Check]:
    """The stage checks of the stage functions the backend has."""
    return [c for c in CHECKS if c.kind == "stage" and c.name[len("stage_"):] in info.stages]


def candidates_for(info: BackendInfo) -> list[str]:
    """Observable deviations that change the backend's profile and that it could show: with a
    render that runs here, any; otherwise those of the stages its stage functions compute."""
    base = refgs.get_profile(info.profile)
    stages = None if info.unavailable_reason is None else {
        STAGE_OF_FUNCTION[c.name[len("stage_"):]] for c in _stage_checks(info)}
    return [n for n, d in DEVIATIONS.items() if d.observable and (info.has_backward or not d.backward_only)
            and (stages is None or d.stage in stages) and apply_deviations(base, {n}) != base]


def _shows(scene: Case, name: str, backward: bool) -> bool:
    """Does deviation ``name`` change the reference on ``scene`` (its witness shows it)?"""
    kind = "backward" if backward else "forward"
    return fingerprint(scene, frozenset(), kind) != fingerprint(scene, frozenset({name}), kind)


def witness_probes(info: BackendInfo, names) -> list[Probe]:
    """The witness scene of each deviation in ``names`` for the backend's profile, kept where it
    shows its deviation under that profile and lies inside the backend's capabilities; judged
    through render (or render_backward), or, when render cannot run here, through each stage
    check of the deviation's stage."""
    out = []
    stage_checks = _stage_checks(info)
    for name in names:
        w = DEVIATIONS[name].witness
        if (w.backward and not info.has_backward) or (w.sh1 is not None and info.max_sh_degree < 1) \
                or (any(w.background) and not info.supports_background) \
                or (w.centre is not None and not info.supports_principal_point):
            continue                                 # outside the backend's declared capabilities
        g, cam, cfg = w.build(info.profile)
        scene = Case(g, cam, cfg, seed=1, label=f"witness:{name}")
        if not _shows(scene, name, w.backward):
            continue
        rounded = scene.rounded(info.dtype)
        if info.unavailable_reason is None:
            out.append(Probe("witness", name, rounded, backward=w.backward, rounding=info.dtype))
        else:
            out += [Probe("witness", name, rounded, c, rounding=info.dtype) for c in stage_checks
                    if STAGE_OF_FUNCTION[c.name[len("stage_"):]] == DEVIATIONS[name].stage]
    return out


def check_probes(ctx: Context, checks, examples: int, seed: int, shrink_failures: bool = True,
                 progress=None, focus=None):
    """Run each diagnosed check on its drawn scenes (no deviation): (failing probes, passing
    probes, {check name: first failure message}, passing check names).  ``focus``: names of the
    checks whose failures are to be explained (``examples`` scenes each; the others
    PASSING_SAMPLE), None for all."""
    failing, passing, messages, ok_checks = [], [], {}, []
    for check in checks:
        n = PASSING_SAMPLE if focus is not None and check.name not in focus else \
            max(1, int(round(examples * check.examples)))
        bad, good = [], []
        for scene in _draw(check, ctx, n, seed):
            p = Probe("check", check.name, scene, check)
            v = judge(ctx, p, ())
            if v.inconclusive:
                continue
            (good if v.ok else bad).append((p, v))
        if bad:
            messages[check.name] = bad[0][1].message()
            failing += [p for p, _ in bad[:KEEP_FAILING]]
            if shrink_failures:
                p0, v0 = bad[0]
                small, _, _ = shrink(lambda c, k=check: judge(ctx, Probe("shrunk", k.name, c.rounded(
                    ctx.dtype), k), ()), p0.scene, v0, SHRINK_BUDGET)
                failing.append(Probe("shrunk", check.name, small.rounded(ctx.dtype), check))
        elif good:
            ok_checks.append(check.name)
            passing.append(good[0][0])
        if progress is not None:
            progress(check.name, "fail" if bad else "pass" if good else "inconclusive")
    return failing, passing, messages, ok_checks


def verify(ctx: Context, deviations, failing_checks, passing_checks, examples: int, seed: int) -> dict:
    """Fresh scenes (seed + 1) of the failing checks and a sample of the passing ones under
    ``deviations``: {"explained": [...], "unexplained": [{check, message}], "new_failures": [...]}."""
    by = {c.name: c for c in CHECKS}
    out = {"explained": [], "unexplained": [], "new_failures": []}
    for name in failing_checks:
        check = by[name]
        n = max(1, int(round(examples * check.examples)))
        verdicts = [judge(ctx, Probe("check", name, s, check), deviations)
                    for s in _draw(check, ctx, n, seed + 1)]
        judged = [v for v in verdicts if not v.inconclusive]
        bad = [v for v in judged if not v.ok]
        if judged and not bad:
            out["explained"].append(name)
        else:
            msg = bad[0].message() if bad else "no example could be judged"
            out["unexplained"].append({"check": name, "message": msg[:500]})
    for name in passing_checks:
        check = by[name]
        for s in _draw(check, ctx, PASSING_SAMPLE, seed + 1):
            v = judge(ctx, Probe("check", name, s, check), deviations)
            if not v.inconclusive and not v.ok:
                out["new_failures"].append({"check": name, "message": v.message()[:500]})
                break
    return out


def stage_probe_list(info: BackendInfo) -> list[Probe]:
    """The stage probes (oracle/stage_probes.py) inside the backend's declared capabilities,
    rounded to its dtype; none when its render cannot run here."""
    if info.unavailable_reason is not None:
        return []
    out = []
    for p, case in stage_probe_cases(info.profile):
        w = p.witness
        if (w.sh1 is not None and info.max_sh_degree < 1) or (any(w.background) and not info.supports_background):
            continue
        out.append(Probe("stage", p.name, case.rounded(info.dtype), rounding=info.dtype))
    return out


def _rows(search: DistanceSearch, found: frozenset) -> dict:
    """The residual rows by kind of probe: stage probes, witnesses, check scenes."""
    rows = {"stage": [], "witness": [], "check": []}
    for p, r in zip(search.probes, search.residual(found)):
        if p.source == "stage":
            sp = STAGE_PROBES[p.name]
            r.update(stage=sp.stage, clauses=list(sp.clauses), adds=sp.adds, base=sp.base)
            rows["stage"].append(r)
        elif p.source == "witness":
            rows["witness"].append(r)
        else:
            r.update(check=p.check.name, kind=p.check.kind)
            rows["check"].append(r)
    return rows


def _pictures(ctx: Context, search: DistanceSearch, found: frozenset, rows: dict, folder) -> None:
    """Draw each stage probe against the plain reference, and each probe of a stage where the
    outputs still part under the set; file names go into the rows (``picture``, ``residual_picture``)."""
    folder = Path(folder)
    by_name = {p.name: p for p in search.probes if p.source == "stage"}
    for r in rows["stage"]:
        p = by_name[r["name"]]
        pic = draw_probe(ctx, p, (), folder / f"stage-{p.name}.png")
        r["picture"] = pic.name if pic is not None else None
        if r["status"] == "differ" and found:
            pic = draw_probe(ctx, p, found, folder / f"stage-{p.name}-residual.png")
            r["residual_picture"] = pic.name if pic is not None else None


def diagnose(backend, *, examples: int = DEFAULT_EXAMPLES, seed: int = 0, checks=None,
             witnesses: bool = True, stage_probes: bool = True, shrink_failures: bool = True,
             verify_set: bool = True, progress=None, focus=None, extra=(),
             timeout: float | None = None, pictures=None) -> dict:
    """Find the set of catalogued deviations that brings the reference closest to the backend
    (module docstring).  ``backend``: a ``module:object`` spec (loaded in this process), a
    BackendInfo (an isolated worker's, or in this process) or a backend object.  ``checks``:
    Check objects or names (default: every check; those not of a diagnosed kind are run and, if
    they fail, listed under ``not_diagnosed``).  ``focus``: the checks whose failures matter
    (oracle/triage.py passes a run's failing checks; the others get PASSING_SAMPLE scenes);
    ``extra``: (check name, Case) failing scenes to use as probes; ``timeout``: seconds of
    backend time per call of an isolated backend; ``pictures``: a folder to draw the stage
    probes into (oracle/diagnosis_page.py shows them).  Returns a JSON-ready dict; ``summary``
    is the one-line verdict, ``residual`` what is left (oracle/residual.py)."""
    t0 = time.perf_counter()
    info = backend_info(backend)
    ctx = plain_context(info, timeout)
    by = {c.name: c for c in CHECKS}
    chosen = list(CHECKS) if checks is None else [by[c] if isinstance(c, str) else c for c in checks]
    runnable = [c for c in chosen if c.kind in DIAGNOSED_KINDS and c.unavailable(ctx) is None]
    failing, passing, messages, ok_checks = check_probes(ctx, runnable, examples, seed,
                                                         shrink_failures, progress, focus)
    for name, case in extra:
        p = Probe("run", name, case.rounded(ctx.dtype), by[name])
        v = judge(ctx, p, ())
        if not v.inconclusive and not v.ok:
            failing.append(p)
            messages.setdefault(name, v.message())
            ok_checks = [c for c in ok_checks if c != name]
    not_diagnosed = _not_diagnosed(ctx, [c for c in chosen if c.kind not in DIAGNOSED_KINDS],
                                   examples, seed)
    cands = candidates_for(info)
    small = (stage_probe_list(info) if stage_probes else []) + \
        (witness_probes(info, cands) if witnesses else [])
    # the small scenes first (they tell deviations apart), then every probe from there
    search = DistanceSearch(ctx, small, cands)
    found = search.run()
    if failing:
        search.add(failing + passing)
        found = search.run(start=found)
    rows = _rows(search, found)
    if pictures is not None:
        _pictures(ctx, search, found, rows, pictures)
    loc = localise(rows["stage"], rows["check"])
    ver = verify(ctx, found, sorted(messages), ok_checks, examples, seed) if verify_set else None
    w_diff = {r["name"] for r in rows["witness"] if r["before"] == "differ"}
    w_left = {r["name"] for r in rows["witness"] if r["status"] == "differ"}
    result = {
        "backend": {"spec": info.spec, "name": info.name, "version": info.version,
                    "profile": info.profile, "dtype": info.dtype},
        "deviations": [n for n in DEVIATIONS if n in found],
        "details": [{"name": n, "label": DEVIATIONS[n].label, "stage": DEVIATIONS[n].stage,
                     "clause": DEVIATIONS[n].clause, "who": DEVIATIONS[n].who}
                    for n in DEVIATIONS if n in found],
        "failing_checks": sorted(messages), "failure_messages": messages,
        "passing_checks": ok_checks, "not_diagnosed": not_diagnosed,
        "stage_probes": rows["stage"],
        "witnesses": {"differing": sorted(w_diff),
                      "agreeing": sorted({r["name"] for r in rows["witness"]} - w_diff),
                      "explained": sorted(w_diff - w_left)},
        "residual": {"summary": residual_summary(loc), **loc, "probes": rows["check"] + rows["witness"]},
        "search": {"trace": search.trace, "evaluations": search.evaluations, "candidates": cands,
                   "probes": len(search.probes), "distance_before": round(search.total(frozenset()), 3),
                   "distance_after": round(search.total(found), 3), "margin": search.margin},
        "verification": ver,
        "settings": {"examples": examples, "seed": seed, "witnesses": witnesses,
                     "stage_probes": stage_probes, "shrink": shrink_failures,
                     "backend_in_process": info.session is None,
                     "render_available": info.unavailable_reason is None},
        "duration_s": round(time.perf_counter() - t0, 2),
    }
    result["summary"] = summary_line(result)
    return result


def _not_diagnosed(ctx: Context, checks, examples: int, seed: int) -> list:
    """Checks of other kinds (invalid input, reference-only) that fail: they are reported, not
    explained (no deviation makes a backend accept invalid input)."""
    out = []
    for check in checks:
        if check.kind == "reference" or check.unavailable(ctx) is not None:
            continue
        n = max(1, int(round(examples * check.examples)))
        for scene in _draw(check, ctx, n, seed):
            try:
                v = check.evaluate(ctx, scene)
            except Exception as exc:
                v = Verdict([problem("oracle", f"{type(exc).__name__}: {exc}")])
            if not v.inconclusive and not v.ok:
                out.append({"check": check.name, "kind": check.kind, "message": v.message()[:300]})
                break
    return out


def summary_line(result: dict) -> str:
    """"behaves like the reference with {...}: explains X of Y failing checks, Z new failures"
    and, when something is left, where the outputs first part."""
    names = result["deviations"]
    n_fail = len(result["failing_checks"])
    ver = result.get("verification")
    wit = result["witnesses"]["differing"]
    stage_diff = [r for r in result.get("stage_probes", []) if r["before"] == "differ"]
    if not n_fail and not wit and not stage_diff:
        return "agrees with the reference on every diagnosed check, witness and stage probe: nothing to explain"
    head = (f"behaves like the reference with {label(names)}" if names else
            "no set of catalogued deviations explains its failures")
    res = result.get("residual") or {}
    tail = f"; {res['summary']}" if res.get("first") else ""
    if ver is None:
        return (f"{head} ({len(result['witnesses']['explained'])} of {len(wit)} differing "
                f"witnesses agree){tail}")
    return (f"{head}: explains {len(ver['explained'])} of {n_fail} failing checks, "
            f"{len(ver['new_failures'])} new failures{tail}")


def summary_text(result: dict) -> str:
    """The diagnosis as text (what ``python -m oracle diagnose`` prints): the stage probes'
    verdicts, the named set, what is left by stage, the time taken."""
    b = result["backend"]
    where = "in-process" if result["settings"].get("backend_in_process", True) else "in a worker"
    lines = [f"diagnosis of {b['spec'] or b['name']} ({b['profile']}, {b['dtype']}); "
             f"backend run {where}, {result['duration_s']} s", result["summary"]]
    sp = result.get("stage_probes", [])
    if sp:
        lines.append("  stage probes (without deviations -> under the set):")
        lines += [f"    {r['name']:<17} {r['stage']:<3} {', '.join(r['clauses']):<16} "
                  f"{r['before']:>6} -> {r['status']:<6} distance {r['distance_before']:.2f} -> "
                  f"{r['distance']:.2f}" for r in sp]
    if result["details"]:
        lines.append("  the named set:")
    for d in result["details"]:
        lines.append(f"    {d['name']:<26} {d['stage']} {d['clause']:<7} {d['label']}")
    ver = result.get("verification") or {}
    for u in ver.get("unexplained", []):
        lines.append(f"  unexplained: {u['check']}: {u['message'][:200]}")
    for u in ver.get("new_failures", []):
        lines.append(f"  new failure under the set: {u['check']}: {u['message'][:200]}")
    for u in result["not_diagnosed"]:
        lines.append(f"  not diagnosed ({u['kind']} check): {u['check']}: {u['message'][:160]}")
    w = result["witnesses"]
    lines.append(f"  witnesses: {len(w['differing'])} differ without deviations, "
                 f"{len(w['explained'])} of them agree under the set")
    res = result.get("residual") or {}
    if res:
        lines.append(f"  what is left: {res['summary']}")
        for stage in res.get("stages", []):
            lines += [f"    {e['sentence']}" for e in res["by_stage"][stage]]
    s = result["search"]
    lines.append(f"  search: distance {s['distance_before']} -> {s['distance_after']} over "
                 f"{s['probes']} probes, {s['evaluations']} judgements; {result['duration_s']} s")
    return "\n".join(lines)


def run_cli(a) -> int:
    """``python -m oracle diagnose`` (oracle/__main__.py): the backend in a worker process
    (oracle/isolation.py); print the diagnosis, write ``diagnosis.json`` and ``diagnosis.txt`` to
    ``--report`` if given.  Exit 0 when every failing check and differing witness is explained
    with no new failure, 1 otherwise, 2 on a usage error."""
    from .isolation import open_backend

    try:
        if a.max_examples < 1:
            raise BackendError(f"--max-examples: expected a positive integer, got {a.max_examples}")
        info = open_backend(a.backend, a.memory_limit)
    except BackendError as exc:
        print(f"oracle: error: {exc}", file=sys.stderr)
        return 2
    try:
        result = diagnose(info, examples=a.max_examples, seed=a.seed,
                          checks=[] if a.no_checks else None, timeout=a.timeout or None,
                          pictures=Path(a.report) / PICTURES if a.report else None,
                          progress=lambda n, st: print(f"  {n:<28} {st}", file=sys.stderr, flush=True))
    finally:
        info.session.close()
    print(summary_text(result))
    if a.report:
        from .html import write_diagnosis_page

        folder = Path(a.report)
        atomic_write_json(folder / "diagnosis.json", result)
        atomic_write_text(folder / "diagnosis.txt", summary_text(result) + "\n")
        page = write_diagnosis_page(result, folder)
        print(f"diagnosis: {folder / 'diagnosis.json'}, {folder / 'diagnosis.txt'} and {page}")
    ver = result["verification"] or {}
    w = result["witnesses"]
    left = ver.get("unexplained") or ver.get("new_failures") or len(w["explained"]) < len(w["differing"]) \
        or result["residual"]["first"] is not None
    return 1 if left else 0


__all__ = ["Probe", "candidates_for", "check_probes", "diagnose", "explains", "judge",
           "plain_context", "stage_probe_list", "summary_line", "summary_text", "verify",
           "witness_probes", "with_deviations"]
