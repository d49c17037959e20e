"""Which named deviations explain a backend's failures (docs/spec/deviations.md, DEV-02).

    result = diagnose("oracle.meta.deviant:gsplat_as_inria")     # a spec, BackendInfo or object
    result["summary"]   # "behaves like the reference with {...}: explains 9 of 9 failing checks,
                        #  0 new failures"

One scene at a time: the backend's output against the float64 reference rendered with a set of
deviations on (``RenderConfig.deviations``), judged by the checks' own comparisons and the
tolerance table (oracle/explain.py, oracle/evaluate.py, oracle/tolerances.py).  The backend's
outputs are memoised per scene (only the reference changes while the search runs); given a
BackendInfo of an isolated worker (oracle/isolation.py ``open_backend``, what ``python -m oracle
diagnose`` and ``check --diagnose`` use) the backend runs there, so a backend that crashes or
hangs costs the scene it was on, not the diagnosis.  Steps: probes -- scenes of every
render-level and stage check (the first failing one also shrunk, oracle/shrink.py), the failing
scenes of a check run when given (``extra``), and the witness scene of every deviation
(refgs/deviations.py; for a backend whose render cannot run here, judged through its stage
functions); greedy forward selection of a single deviation, else a pair, then pruning;
verification on fresh scenes.  A failure no set explains is reported as unexplained, never
guessed.
"""
from __future__ import annotations

import itertools
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, Phase, Verbosity, given
from hypothesis import seed as hseed
from hypothesis import settings as hsettings

import refgs
from refgs.deviations import DEVIATIONS, apply_deviations, incompatible, label
from refgs.io.atomic import atomic_write_json, atomic_write_text

from .checks import CHECKS, Check
from .compare import problem
from .evaluate import Context, Verdict
from .explain import (INVARIANT_WAIVERS, Probe, backend_info, explains, fingerprint, judge, outcome,
                      plain_context, reference_fingerprint, with_deviations)
from .protocol import BackendError, BackendInfo, Case
from .shrink import shrink

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
#: at most this many single deviations (those that move the unexplained probes most) are paired
MAX_PAIRED = 12
#: the stage of the catalogue (Deviation.stage) each stage function computes
STAGE_OF_FUNCTION = {"covariance": "COV", "projection": "PRJ", "sh": "SH", "composite": "RAS"}


@dataclass(frozen=True)
class Score:
    explained: int                   # failing probes that agree under the set
    broken: int                      # agreeing probes that differ under the set
    residual: float                  # sum of log10(worst ratio) over failing probes still differing

    @property
    def net(self) -> int:
        return self.explained - self.broken


class Search:
    """Greedy forward selection over deviation sets (module docstring, step 2)."""

    def __init__(self, ctx: Context, failing: list, passing: list, candidates: list):
        self.ctx, self.failing, self.passing, self.candidates = ctx, failing, passing, candidates
        self.cache: dict = {}
        self.trace: list = []
        self.evaluations = 0

    def outcome(self, i: int, probes: list, deviations: frozenset) -> tuple[str, float]:
        """The probe's outcome under ``deviations``; sets under which the reference renders the
        probe identically share one judgement (the backend is judged against those outputs)."""
        key = (id(probes), i, deviations)
        if key not in self.cache:
            fp = (id(probes), i, reference_fingerprint(probes[i], deviations),
                  frozenset(o for o, devs in INVARIANT_WAIVERS.items() if devs & deviations))
            if fp not in self.cache:
                self.evaluations += 1
                self.cache[fp] = outcome(judge(self.ctx, probes[i], deviations))
            self.cache[key] = self.cache[fp]
        return self.cache[key]

    def explained(self, s: frozenset) -> tuple[int, float]:
        n, residual = 0, 0.0
        for i in range(len(self.failing)):
            status, ratio = self.outcome(i, self.failing, s)
            if status == "agree":
                n += 1
            elif status == "differ":
                residual += float(np.log10(max(ratio, 1.0)))
        return n, residual

    def broken(self, s: frozenset) -> int:
        return sum(self.outcome(i, self.passing, s)[0] == "differ" for i in range(len(self.passing)))

    def score(self, s: frozenset) -> Score:
        n, residual = self.explained(s)
        return Score(n, self.broken(s) if s else 0, residual)

    def _best(self, options: list, current_set: frozenset, current: Score):
        """The option of highest net score above ``current``.  Options are rated by the failing
        probes they newly explain (an upper bound of what they add) and scored in full, lazily,
        only while that bound can still beat the best so far."""
        open_ = [i for i in range(len(self.failing))
                 if self.outcome(i, self.failing, current_set)[0] != "agree"]

        def gain(s):
            n, residual = 0, 0.0
            for i in open_:
                status, ratio = self.outcome(i, self.failing, s)
                n += status == "agree"
                residual += float(np.log10(max(ratio, 1.0))) if status == "differ" else 0.0
            return n, residual

        rated = sorted(((gain(s), s) for s in options), key=lambda x: (-x[0][0], x[0][1], sorted(x[1])))
        best = None
        for (n, _), s in rated:
            if n == 0 or current.explained + n <= (best[1].net if best else current.net):
                break                                      # cannot beat the best any more
            sc = self.score(s)
            if sc.net > current.net and (best is None or (sc.net, -sc.residual) > (best[1].net, -best[1].residual)):
                best = (s, sc)
        return best

    def _relevant(self, current: frozenset) -> list:
        """Single additions that move the unexplained probes' errors, most first."""
        moved = []
        base = [self.outcome(i, self.failing, current) for i in range(len(self.failing))]
        for d in self.candidates:
            s = current | {d}
            if d in current or incompatible(s):
                continue
            shift = sum(abs(np.log10(max(self.outcome(i, self.failing, s)[1], 1e-300))
                            - np.log10(max(r, 1e-300)))
                        for i, (st, r) in enumerate(base) if st != "agree")
            if shift > 1e-9:
                moved.append((shift, d))
        return [d for _, d in sorted(moved, key=lambda x: (-x[0], x[1]))[:MAX_PAIRED]]

    def run(self, pairs: bool = True, start: frozenset = frozenset()) -> frozenset:
        """Greedy forward selection from ``start`` (module docstring), then pruning."""
        current = frozenset(start)
        sc = self.score(current)
        while sc.explained < len(self.failing):
            singles = [current | {d} for d in self.candidates
                       if d not in current and incompatible(current | {d}) is None]
            best = self._best(singles, current, sc)
            if best is None and pairs:
                rel = self._relevant(current)
                duo = [current | {a, b} for a, b in itertools.combinations(rel, 2)
                       if incompatible(current | {a, b}) is None]
                best = self._best(duo, current, sc)
            if best is None:
                break
            added = sorted(best[0] - current)
            current, sc = best
            self.trace.append({"added": added, "explained": sc.explained, "broken": sc.broken,
                               "of": len(self.failing)})
        pruned = True
        while pruned and current:                        # drop members the others do not need
            pruned = False
            for d in sorted(current):
                s = current - {d}
                alt = self.score(s)
                if alt.net >= sc.net:
                    current, sc, pruned = s, alt, True
                    self.trace.append({"dropped": d, "explained": sc.explained, "broken": sc.broken,
                                       "of": len(self.failing)})
                    break
        return current


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


def diagnose(backend, *, examples: int = DEFAULT_EXAMPLES, seed: int = 0, checks=None,
             witnesses: bool = True, shrink_failures: bool = True, pairs: bool = True,
             verify_set: bool = True, progress=None, focus=None, extra=(),
             timeout: float | None = None) -> dict:
    """Find the smallest set of catalogued deviations under which the reference matches the
    backend (module docstring).  ``backend``: a ``module:object`` spec (loaded in this process),
    a BackendInfo (an isolated worker's, or in this process) or a backend object.  ``checks``:
    Check objects or names (default: every check; those not of a diagnosed kind are run and, if
    they fail, listed under ``not_diagnosed``).  ``focus``: the checks whose failures matter
    (oracle/triage.py passes a run's failing checks; the others get PASSING_SAMPLE scenes);
    ``extra``: (check name, Case) failing scenes to use as probes; ``timeout``: seconds of
    backend time per call of an isolated backend.  Returns a JSON-ready dict; ``summary`` is the
    one-line verdict."""
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
    wit = witness_probes(info, cands) if witnesses else []
    status = [outcome(judge(ctx, p, ()))[0] for p in wit]        # inconclusive ones are left out
    w_fail = [p for p, st in zip(wit, status) if st == "differ"]
    w_pass = [p for p, st in zip(wit, status) if st == "agree"]
    # witnesses first (small scenes that tell deviations apart), then every probe from there
    start = Search(ctx, w_fail, w_pass, cands).run(pairs=pairs) if w_fail and failing else frozenset()
    search = Search(ctx, failing + w_fail, passing + w_pass, cands)
    found = search.run(pairs=pairs, start=start) if search.failing else frozenset()
    ver = verify(ctx, found, sorted(messages), ok_checks, examples, seed) if verify_set else None
    w_ok = sorted({p.name for k, p in enumerate(w_fail)
                   if search.outcome(len(failing) + k, search.failing, found)[0] == "agree"}
                  - {p.name for k, p in enumerate(w_fail)
                     if search.outcome(len(failing) + k, search.failing, found)[0] != "agree"})
    result = {
        "backend": {"spec": info.spec, "name": info.name, "version": info.version,
                    "profile": info.profile, "dtype": info.dtype},
        "deviations": [n for n in DEVIATIONS if n in found],
        "details": [{"name": n, "label": DEVIATIONS[n].label, "stage": DEVIATIONS[n].stage,
                     "clause": DEVIATIONS[n].clause, "who": DEVIATIONS[n].who}
                    for n in DEVIATIONS if n in found],
        "failing_checks": sorted(messages), "failure_messages": messages,
        "passing_checks": ok_checks, "not_diagnosed": not_diagnosed,
        "witnesses": {"differing": sorted({p.name for p in w_fail}),
                      "agreeing": sorted({p.name for p in w_pass}), "explained": w_ok},
        "search": {"trace": search.trace, "evaluations": search.evaluations, "candidates": cands,
                   "probes_failing": len(search.failing), "probes_agreeing": len(search.passing)},
        "verification": ver,
        "settings": {"examples": examples, "seed": seed, "witnesses": witnesses, "pairs": pairs,
                     "shrink": shrink_failures, "backend_in_process": info.session is None,
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
    """"behaves like the reference with {...}: explains X of Y failing checks, Z new failures"."""
    names = result["deviations"]
    n_fail = len(result["failing_checks"])
    ver = result.get("verification")
    wit = result["witnesses"]["differing"]
    if not n_fail and not wit:
        return "agrees with the reference on every diagnosed check and witness: nothing to explain"
    head = (f"behaves like the reference with {label(names)}" if names else
            "no set of catalogued deviations explains its failures")
    if ver is None:
        return f"{head} ({len(result['witnesses']['explained'])} of {len(wit)} differing witnesses agree)"
    return (f"{head}: explains {len(ver['explained'])} of {n_fail} failing checks, "
            f"{len(ver['new_failures'])} new failures")


def summary_text(result: dict) -> str:
    """The diagnosis as a few lines of text (what ``python -m oracle diagnose`` prints)."""
    b = result["backend"]
    where = "in-process" if result["settings"].get("backend_in_process", True) else "in a worker"
    lines = [f"diagnosis of {b['spec'] or b['name']} ({b['profile']}, {b['dtype']}); "
             f"backend run {where}, {result['duration_s']} s", result["summary"]]
    for d in result["details"]:
        lines.append(f"  {d['name']:<26} {d['stage']} {d['clause']:<7} {d['label']}")
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
                          progress=lambda n, st: print(f"  {n:<28} {st}", file=sys.stderr, flush=True))
    finally:
        info.session.close()
    print(summary_text(result))
    if a.report:
        atomic_write_json(Path(a.report) / "diagnosis.json", result)
        atomic_write_text(Path(a.report) / "diagnosis.txt", summary_text(result) + "\n")
        print(f"diagnosis: {Path(a.report) / 'diagnosis.json'} and {Path(a.report) / 'diagnosis.txt'}")
    ver = result["verification"] or {}
    w = result["witnesses"]
    left = ver.get("unexplained") or ver.get("new_failures") or len(w["explained"]) < len(w["differing"])
    return 1 if left else 0


__all__ = ["Probe", "Search", "candidates_for", "check_probes", "diagnose", "explains",
           "judge", "plain_context", "summary_line", "summary_text", "verify", "witness_probes",
           "with_deviations"]
