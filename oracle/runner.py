"""Run checks against a backend with hypothesis; shrink failures; collect results (ORC-02, ORC-06,
ORC-11, ORC-12).

    result = run_isolated("mod:obj", Settings(max_examples=20, report_dir="out", timeout=300))
    report = check_backend("mod:obj", Settings(...))    # the same, as the report.json dict
    result = run(load_backend("mod:obj"), Settings())   # in this process (tests, notebooks)
    result.exit_status      # 0 exactly when every check is pass, n/a, not provided or known

:func:`run_isolated` (what ``python -m oracle check`` uses) runs the backend in a worker process
(oracle/isolation.py): a check whose worker dies is ``crash``, one that outlives
``Settings.timeout`` seconds of backend time is ``timeout``, and the run goes on with a fresh
worker.  Each check becomes a hypothesis property over its case strategy (``database=None``,
seeded, no deadline).  A failing example is shrunk by hypothesis, then by oracle/shrink.py
keeping the failure's mechanism; the smallest case is written as a reproducer
``<report_dir>/failures/<check>.npz`` with a one-line replay command, and the clauses the failure
is evidence against are blamed (oracle/blame.py).
"""
from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, Phase, Verbosity, given, reject
from hypothesis.errors import Unsatisfiable
from hypothesis import seed as hseed
from hypothesis import settings as hsettings

from . import __version__ as ORACLE_VERSION
from . import blame as bl
from . import known as kd
from .checks import CHECKS, Check
from .clauses import load_clauses
from .compare import problem
from .evaluate import Context, Verdict
from .isolation import DEFAULT_MEMORY_LIMIT_MIB, WorkerLost, open_backend
from .protocol import BackendInfo, Case
from .report import save_case, scene_parameters
from .shrink import DEFAULT_BUDGET, StopShrinking, shrink

#: check statuses that do not fail a run (ORC-02)
OK_STATUSES = ("pass", "n/a", "not provided", "known")
#: problem sorts that make a failing example an ``error`` (malformed output, an exception)
#: rather than a ``fail`` (a wrong value)
ERROR_KINDS = bl.STRUCTURAL + ("dtype", "exception")


@dataclass
class Settings:
    """How to run: examples per check, seed, shrinking, where reproducers and reports go, the
    backend's time budget per check (seconds, None: no limit; enforced only for an isolated
    backend), the worker's memory limit (MiB, 0: none) and known differences from a file."""

    max_examples: int = 20
    seed: int = 0
    shrink: bool = True
    shrink_budget: int = DEFAULT_BUDGET
    report_dir: str | None = None
    clauses: tuple = ()
    timeout: float | None = None
    memory_limit_mib: int | None = DEFAULT_MEMORY_LIMIT_MIB
    known_differences: tuple = ()

    def to_json(self) -> dict:
        return {"max_examples": self.max_examples, "seed": self.seed, "shrink": self.shrink,
                "shrink_budget": self.shrink_budget, "report_dir": self.report_dir,
                "clauses": list(self.clauses), "timeout_s": self.timeout,
                "memory_limit_mib": self.memory_limit_mib,
                "known_differences": [dict(e) for e in self.known_differences]}


@dataclass
class CheckResult:
    check: Check
    status: str
    reason: str = ""
    examples: int = 0
    worst_ratio: float | None = None
    worst: dict | None = None
    failure: dict | None = None
    inconclusive: int = 0
    ties: dict = field(default_factory=dict)
    provided: set = field(default_factory=set)
    clause_status: dict = field(default_factory=dict)
    duration: float = 0.0
    #: {"blamed": {clause: why}, "spared": {clause: why}} for a fail or error (oracle/blame.py)
    blame: dict | None = None
    #: the known-difference entries naming this check (oracle/known.py)
    known: list = field(default_factory=list)
    #: arrays for the pictures of a failure (oracle/pictures.py): the smallest case, the
    #: reference's and the backend's outputs on it; not part of report.json
    evidence: dict | None = None
    #: the failing case as hypothesis found it, before oracle/shrink.py (a diagnosis shrinks it
    #: again keeping its deviation signature, oracle/triage.py); not part of report.json
    unshrunk: Case | None = None

    def to_json(self) -> dict:
        w = self.worst_ratio
        return {"name": self.check.name, "clauses": list(self.check.clauses), "kind": self.check.kind,
                "doc": self.check.doc, "status": self.status, "reason": self.reason,
                "examples": self.examples, "inconclusive": self.inconclusive,
                "worst_ratio": None if w is None else (w if np.isfinite(w) else "inf"),
                "worst": self.worst, "ties": self.ties, "provided": sorted(self.provided),
                "clause_status": self.clause_status, "blame": self.blame, "known": self.known,
                "failure": self.failure, "duration_s": round(self.duration, 3)}


@dataclass
class RunResult:
    backend: BackendInfo
    settings: Settings
    results: list
    clauses: dict
    started: str
    duration: float
    oracle_version: str = ORACLE_VERSION
    #: the diagnosis of the failing checks (oracle/triage.py), when one was asked for: the
    #: diagnosis.json dict, or {"available": False, "reason": ...}
    diagnosis: dict | None = None

    @property
    def failed_clauses(self) -> list[str]:
        from .report import clause_table
        return [c for c, row in clause_table(self.results, self.clauses).items()
                if row["status"] not in OK_STATUSES]

    @property
    def exit_status(self) -> int:
        return 1 if any(r.status not in OK_STATUSES for r in self.results) else 0


class _Falsified(AssertionError):
    """Raised inside the hypothesis property when a case fails the check."""


def safe_evaluate(check: Check, ctx: Context, scene: Case) -> Verdict:
    """``check.evaluate``; an exception of the oracle's own becomes a failed comparison."""
    try:
        return check.evaluate(ctx, scene)
    except Exception as exc:      # an oracle-side error: report it as a failure, never hide it
        tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
        return Verdict([problem("oracle", f"evaluating {check.name} raised "
                                          f"{type(exc).__name__}: {exc} ({tb})", "oracle")])


def verdict_status(v: Verdict) -> str:
    """``error`` when a failing comparison is a malformed output or an exception, else ``fail``."""
    return "error" if any(c.kind in ERROR_KINDS for c in v.comparisons if not c.ok) else "fail"


def run_check(ctx: Context, check: Check, settings: Settings, known=()) -> CheckResult:
    """Run one check (see module docstring); ``known``: known-difference entries."""
    t0 = time.perf_counter()
    why = check.unavailable(ctx)
    if why is not None:
        return CheckResult(check, why[0], why[1])
    session = ctx.backend.session
    if session is not None:
        session.begin_check(settings.timeout)
    state = {"n": 0, "worst": None, "fail": None, "provided": set(), "ties": {},
             "inconclusive": 0, "why": "", "current": None}

    def prop(scene):
        scene = scene.rounded(ctx.dtype)
        state["n"] += 1
        state["current"] = scene
        v = safe_evaluate(check, ctx, scene)
        state["provided"] |= v.provided
        for k, info in v.ties.items():
            agg = state["ties"].setdefault(k, {"max_pixels_in_band": 0, "by_reason": {}})
            agg["max_pixels_in_band"] = max(agg["max_pixels_in_band"], info["pixels_in_band"])
            if "ill_conditioned_gaussians" in info:
                agg["max_ill_conditioned_gaussians"] = max(agg.get("max_ill_conditioned_gaussians", 0),
                                                           info["ill_conditioned_gaussians"])
            for r, cnt in info["by_reason"].items():
                agg["by_reason"][r] = agg["by_reason"].get(r, 0) + cnt
        agg_flips = sum(c.ties.get("flips", 0) for c in v.comparisons)
        if v.ties:
            state["ties"].setdefault("flips", 0)
            state["ties"]["flips"] += agg_flips
        if v.inconclusive:                # more near-ties than the budget: not judged (ORC-04)
            state["inconclusive"] += 1
            state["why"] = v.inconclusive
            reject()
        w = v.worst
        if w is not None and (state["worst"] is None or w.ratio > state["worst"].ratio) and v.ok:
            state["worst"] = w
        if not v.ok:
            state["fail"] = (scene, v)
            raise _Falsified(v.message())

    n_examples = max(1, int(round(settings.max_examples * check.examples)))
    phases = [Phase.explicit, Phase.generate] + ([Phase.shrink] if settings.shrink else [])
    test = given(scene=check.scenes(ctx))(prop)
    test = hsettings(max_examples=n_examples, deadline=None, database=None, derandomize=False,
                     phases=phases, suppress_health_check=list(HealthCheck),
                     verbosity=Verbosity.quiet, report_multiple_bugs=False, print_blob=False)(test)
    test = hseed(settings.seed)(test)
    result = CheckResult(check, "pass")
    lost = None
    try:
        test()
    except _Falsified:
        result.status = verdict_status(state["fail"][1])
    except WorkerLost as exc:
        lost = exc
    except Unsatisfiable:
        result.status = "fail"
        result.failure = {"message": f"no example could be judged: every case held more near-ties "
                                     f"than the budget (last: {state['why']})", "scene": None}
    except Exception as exc:          # hypothesis could not generate, or similar: an oracle error
        result.status = "fail"
        state["fail"] = None
        result.failure = {"message": f"the check could not run: {type(exc).__name__}: {exc}",
                          "scene": None}
    result.examples = state["n"] - state["inconclusive"]
    result.inconclusive = state["inconclusive"]
    result.provided = state["provided"]
    result.ties = state["ties"]
    if state["worst"] is not None:
        result.worst_ratio = float(state["worst"].ratio)
        result.worst = state["worst"].to_json()
    if lost is not None:
        _record_lost(ctx, check, settings, result, lost, state["current"], state["fail"])
    elif result.status in ("fail", "error") and state["fail"] is not None:
        record_failure(ctx, check, settings, result, *state["fail"])
    elif result.status == "fail":
        result.blame = {"blamed": {c: "the check could not judge any case" for c in check.clauses},
                        "spared": {}}
    for cid, outs in check.clause_outputs.items():
        if result.status == "pass" and not (set(outs) & result.provided):
            result.clause_status[cid] = "not provided"
    kd.apply(result, known)
    result.duration = time.perf_counter() - t0
    return result


def _reproducer(ctx, check, settings, failure, scene, message):
    if settings.report_dir:
        path = Path(settings.report_dir) / "failures" / f"{check.name}.npz"
        save_case(path, scene, check=check.name, clauses=",".join(check.clauses),
                  backend=ctx.backend.spec, message=message[:2000])
        failure["reproducer"] = str(path)
        failure["replay"] = (f"python -m oracle replay {path} --backend "
                             f"{ctx.backend.spec or '<module:object>'}")


def _evidence(ctx, check, scene, with_backend: bool) -> dict:
    """The arrays of the pictures of a failure: the reference's (and the backend's) outputs on
    the smallest case.  A backend that dies or hangs now leaves the reference alone."""
    ctx.capture = {}
    try:
        if with_backend:
            safe_evaluate(check, ctx, scene)
        else:
            from .evaluate import reference
            ctx.capture["forward"] = {"ref": reference(scene)}
    except WorkerLost:
        pass
    except Exception:                                  # the reference rejects it: no pictures
        pass
    finally:
        got, ctx.capture = ctx.capture, None
    return {"case": scene, **got}


def _record_lost(ctx, check, settings, result, lost, scene, earlier):
    """The check's worker died or timed out on ``scene``: status crash / timeout, every clause."""
    result.status = lost.kind
    msg = f"{lost.kind}: {lost.reason}"
    if earlier is not None:
        msg += f" (after an example had failed: {earlier[1].message()[:300]})"
    failure = {"message": msg, "comparison": None, "reproducer": None, "replay": None,
               "scene": None if scene is None else scene.summary(),
               "parameters": [] if scene is None else scene_parameters(scene), "shrink": None}
    result.worst_ratio = float("inf")
    if scene is not None:
        _reproducer(ctx, check, settings, failure, scene, msg)
        result.evidence = _evidence(ctx, check, scene, with_backend=False)
    result.failure = failure
    result.blame = {"blamed": {cid: f"the check ended in a {lost.kind}" for cid in check.clauses},
                    "spared": {}}


def shrink_failure(ctx, check, settings, scene, verdict, signature=None):
    """oracle/shrink.py on a failing ``scene`` of ``check``, keeping the failure's mechanism and,
    given a started ``signature`` (oracle/explain.py ``Signature``), its deviation signature:
    ``(case, verdict, ShrinkStats)``."""
    def evaluate(s):
        try:
            if signature is not None:
                return signature.evaluate(s)
            return check.evaluate(ctx, s.rounded(ctx.dtype))
        except WorkerLost as lost:
            raise StopShrinking(f"the backend's worker was lost while shrinking: {lost.reason}") from None

    def mechanism(s, v):
        return bl.mechanism(v, bl.facts(s.rounded(ctx.dtype)))

    centred = not ctx.backend.supports_principal_point
    return shrink(evaluate, scene, verdict, settings.shrink_budget, mechanism=mechanism,
                  centred=centred, keep=None if signature is None else signature.keeps)


def record_failure(ctx, check, settings, result, scene, verdict, signature=None):
    """Fill ``result`` (status, failure, reproducer, blame, evidence) from the failing ``scene``
    of ``check``, shrunk first when ``settings.shrink`` (with the deviation ``signature`` when
    given)."""
    stats = None
    result.unshrunk = scene
    if settings.shrink:
        scene, verdict, stats = shrink_failure(ctx, check, settings, scene, verdict, signature)
    rounded = scene.rounded(ctx.dtype)
    result.status = verdict_status(verdict)
    w = verdict.worst
    result.worst_ratio = float(w.ratio) if w is not None else float("inf")
    failure = {"message": verdict.message(), "comparison": w.to_json() if w is not None else None,
               "scene": scene.summary(), "parameters": scene_parameters(scene),
               "shrink": stats.to_json() if stats else None, "reproducer": None, "replay": None}
    _reproducer(ctx, check, settings, failure, scene, verdict.message())
    result.failure = failure
    try:
        facts = bl.facts(rounded)
    except Exception:                                  # the reference rejects the case
        facts = None
    blamed, spared = bl.blame(check.clauses, verdict, facts)
    result.blame = {"blamed": blamed, "spared": spared}
    if not blamed:
        result.blame["unattributed"] = ("the failure is no evidence against a clause this check "
                                        "cites (see spared); other checks judge the failing values")
    for cid in check.clauses:
        result.clause_status[cid] = result.status if cid in blamed else "pass"
    result.evidence = _evidence(ctx, check, rounded, with_backend=True)
    result.evidence["verdict"] = verdict


def run(backend: BackendInfo, settings: Settings | None = None, checks=None, progress=None) -> RunResult:
    """Run ``checks`` (default: all, or those citing ``settings.clauses``) against ``backend``
    (in this process, or isolated when ``backend.session`` is set).  ValueError when a known
    difference names no check or a clause its check does not cite."""
    settings = settings or Settings()
    clauses = load_clauses()
    if checks is None:
        checks = CHECKS
        if settings.clauses:
            want = set(settings.clauses)
            checks = [c for c in CHECKS if want & set(c.clauses)]
    known = tuple(backend.known_differences) + tuple(settings.known_differences)
    kd.validate(known, CHECKS)
    ctx = Context(backend)
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    t0 = time.perf_counter()
    results = []
    for check in checks:
        r = run_check(ctx, check, settings, known)
        results.append(r)
        if progress is not None:
            progress(r)
    return RunResult(backend, settings, results, clauses, started, time.perf_counter() - t0)


def run_isolated(spec: str, settings: Settings | None = None, checks=None, progress=None,
                 after=None) -> RunResult:
    """:func:`run` with the backend ``spec`` in a worker process (oracle/isolation.py).
    BackendError (one line) when it cannot be loaded; the worker is stopped at the end.
    ``after(result, backend)`` runs before that, through the same worker (oracle/triage.py
    ``run_diagnosed`` diagnoses the failing checks there)."""
    settings = settings or Settings()
    backend = open_backend(spec, settings.memory_limit_mib)
    try:
        result = run(backend, settings, checks, progress)
        if after is not None:
            after(result, backend)
        return result
    finally:
        backend.session.close()


def write_reports(result: RunResult, folder) -> tuple:
    """report.json, report.txt (oracle/report.py), diagnosis.json when the run was diagnosed,
    and index.html with its pictures (oracle/html.py) in ``folder``; returns the paths of
    report.json, report.txt and index.html."""
    from refgs.io.atomic import atomic_write_json

    from .html import write_page
    from .report import write_report
    paths = write_report(result, folder)
    if result.diagnosis is not None:
        atomic_write_json(Path(folder) / "diagnosis.json", result.diagnosis)
    return (*paths, write_page(result, folder))


def check_backend(spec: str, settings: Settings | None = None, checks=None, progress=None) -> dict:
    """Run the checks for ``spec`` in isolated workers and return the report.json dict; with
    ``settings.report_dir`` also write report.json, report.txt and index.html there."""
    from .report import to_json
    result = run_isolated(spec, settings, checks, progress)
    if result.settings.report_dir:
        write_reports(result, result.settings.report_dir)
    return to_json(result)
