"""The diagnosis of a check run: which named deviations explain its failing checks, and minimal
cases that keep their deviation signature (docs/spec/deviations.md DEV-02, docs/spec/oracle.md
ORC-06).  ``python -m oracle check --diagnose`` and ``python -m oracle matrix`` use it through
``run_diagnosed``.

    result = run_diagnosed("mod:obj", Settings(...))     # runner.run_isolated, then the diagnosis
    result.diagnosis                                     # the diagnosis.json dict
    result.diagnosis = diagnose_run(result, backend)    # backend: the run's BackendInfo

Diagnosed are the checks whose status is ``fail``, ``error`` or ``known`` (a declared difference
is a failure its author explained in words; the diagnosis names it); ``crash`` and ``timeout``
are listed as not diagnosed (no deviation of the reference crashes).  Steps:

1. oracle/diagnose.py ``diagnose`` through the run's backend (an isolated worker: a backend that
   crashes or hangs costs a scene, not the diagnosis), focused on the failing checks, with the
   run's own failing cases as extra probes;
2. a failing check is *explained* when the set found explains the run's own failing case and,
   when the diagnosis' scenes of that check failed too, its fresh scenes in the verification;
3. the failing case of each explained check is shrunk again from the case hypothesis found,
   keeping the mechanism and the deviation signature (oracle/explain.py ``Signature``): the
   reproducer, the pictures and the failure block are replaced, and ``failure["signature"]``
   names the deviations the minimal case shows.

An exception of the oracle's own becomes ``{"available": False, "reason": ...}``: the run's
report stands without a diagnosis.
"""
from __future__ import annotations

import time
import traceback
from pathlib import Path

from refgs.deviations import DEVIATIONS, label

from . import known as kd
from .diagnose import DEFAULT_EXAMPLES, diagnose
from .evaluate import Context
from .explain import Signature
from .pictures import PICTURES
from .isolation import WorkerLost
from .runner import record_failure, run_isolated

#: check statuses whose failures the diagnosis explains
DIAGNOSED_STATUSES = ("fail", "error", "known")
#: statuses a deviation cannot explain
NOT_DIAGNOSED_STATUSES = ("crash", "timeout")


def run_summary(deviations, explained: int, failing: int, new_failures: int, residual=None) -> str:
    """"behaves like the reference with {...}: explains X of Y failing checks, Z new failures"
    and, when the diagnosis' ``residual`` names a stage, where the outputs first part."""
    if not failing:
        return "nothing to explain: no check failed"
    head = (f"behaves like the reference with {label(deviations)}" if deviations else
            "no set of catalogued deviations explains its failures")
    tail = f"; {residual['summary']}" if residual and residual.get("first") else ""
    return f"{head}: explains {explained} of {failing} failing checks, {new_failures} new failures{tail}"


def unavailable(reason: str) -> dict:
    """The diagnosis block of a run whose diagnosis could not be made."""
    return {"available": False, "reason": reason,
            "summary": f"diagnosis not available: {reason}"}


def diagnose_run(result, backend, progress=None, examples: int = DEFAULT_EXAMPLES) -> dict:
    """The diagnosis of ``result`` (a runner.RunResult) through ``backend`` (its BackendInfo);
    re-shrinks the explained failures in ``result`` (module docstring).  Never raises for an
    error of the diagnosis itself: it is reported as unavailable."""
    try:
        return _diagnose_run(result, backend, progress, examples)
    except WorkerLost as lost:
        return unavailable(f"the backend's worker was lost: {lost.reason}")
    except Exception as exc:
        where = traceback.format_exc(limit=-1).strip().splitlines()
        return unavailable(f"{type(exc).__name__}: {exc} ({where[-3].strip() if len(where) > 2 else ''})")


def _diagnose_run(result, backend, progress, examples: int) -> dict:
    t0 = time.perf_counter()
    settings = result.settings
    failing = [r for r in result.results if r.status in DIAGNOSED_STATUSES]
    skipped = [{"check": r.check.name, "status": r.status,
                "reason": f"a {r.status} is not a difference of values"}
               for r in result.results if r.status in NOT_DIAGNOSED_STATUSES]
    block = {"available": True, "deviations": [], "details": [], "failing": [r.check.name for r in failing],
             "explained": [], "unexplained": [], "not_diagnosed": skipped, "new_failures": [],
             "signatures": {}, "diagnosis": None}
    if not failing:
        block.update(summary=run_summary((), 0, 0, 0), duration_s=round(time.perf_counter() - t0, 2))
        return block
    extra = []
    for r in failing:
        for case in (r.unshrunk, (r.evidence or {}).get("case")):
            if case is not None:
                extra.append((r.check.name, case))
    pictures = Path(settings.report_dir) / PICTURES if settings.report_dir else None
    d = diagnose(backend, examples=examples, seed=settings.seed, focus={r.check.name for r in failing},
                 extra=extra, timeout=settings.timeout, progress=progress, pictures=pictures)
    found = frozenset(d["deviations"])
    ver = d.get("verification") or {}
    fresh_ok = set(ver.get("explained", [])) | (set(r.check.name for r in failing) - set(d["failing_checks"]))
    known = tuple(backend.known_differences) + tuple(settings.known_differences)
    ctx = Context(backend)
    for r in failing:
        case = r.unshrunk if r.unshrunk is not None else (r.evidence or {}).get("case")
        sig = Signature(backend, r.check, found, settings.timeout)
        own = sig.start(case) if case is not None and found else None
        if own is None or r.check.name not in fresh_ok:
            msg = (r.failure or {}).get("message", "")
            why = next((u["message"] for u in ver.get("unexplained", []) if u["check"] == r.check.name), msg)
            block["unexplained"].append({"check": r.check.name, "status": r.status, "message": why[:500]})
            continue
        block["explained"].append(r.check.name)
        if settings.shrink and r.unshrunk is not None:
            status = r.status
            r.clause_status = {}
            record_failure(ctx, r.check, settings, r, r.unshrunk, sig.evaluate(r.unshrunk), signature=sig)
            if status == "known":
                kd.apply(r, known)
        shown = sig.current if sig.current is not None else own
        r.failure["signature"] = {"deviations": [n for n in DEVIATIONS if n in shown], "label": label(shown)}
        block["signatures"][r.check.name] = [n for n in DEVIATIONS if n in shown]
    block.update(deviations=d["deviations"], details=d["details"],
                 new_failures=ver.get("new_failures", []), diagnosis=d,
                 summary=run_summary(found, len(block["explained"]), len(failing),
                                     len(ver.get("new_failures", [])), d["residual"]),
                 duration_s=round(time.perf_counter() - t0, 2))
    return block


def run_diagnosed(spec: str, settings=None, checks=None, progress=None, diagnosis_progress=None):
    """runner.run_isolated on ``spec``, then :func:`diagnose_run` through the same worker:
    the RunResult with its ``diagnosis``."""
    def after(result, backend):
        result.diagnosis = diagnose_run(result, backend, diagnosis_progress)
    return run_isolated(spec, settings, checks, progress, after=after)


__all__ = ["DIAGNOSED_STATUSES", "diagnose_run", "run_diagnosed", "run_summary", "unavailable"]
