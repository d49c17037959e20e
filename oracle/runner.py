"""Run checks against a backend with hypothesis; shrink failures; collect results (ORC-02, ORC-06).

    result = run(load_backend("mod:obj"), Settings(max_examples=20, seed=0, report_dir="out"))
    result.exit_status      # 0 exactly when no clause failed

Each check becomes a hypothesis property over its scene strategy (``database=None``, seeded, no
deadline).  A failing example is shrunk by hypothesis, then by oracle/shrink.py; the smallest
scene is written as a reproducer ``<report_dir>/failures/<check>.npz`` with a one-line replay
command.
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
from .checks import CHECKS, Check
from .clauses import load_clauses
from .compare import problem
from .evaluate import Context, Verdict
from .protocol import BackendInfo, Scene
from .report import save_scene, scene_parameters
from .shrink import DEFAULT_BUDGET, shrink


@dataclass
class Settings:
    """How to run: examples per check, seed, shrinking, where reproducers and reports go."""

    max_examples: int = 20
    seed: int = 0
    shrink: bool = True
    shrink_budget: int = DEFAULT_BUDGET
    report_dir: str | None = None
    clauses: tuple = ()

    def to_json(self) -> dict:
        return {"max_examples": self.max_examples, "seed": self.seed, "shrink": self.shrink,
                "shrink_budget": self.shrink_budget, "report_dir": self.report_dir,
                "clauses": list(self.clauses)}


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

    def to_json(self) -> dict:
        w = self.worst_ratio
        return {"name": self.check.name, "clauses": list(self.check.clauses), "kind": self.check.kind,
                "doc": self.check.doc, "status": self.status, "reason": self.reason,
                "examples": self.examples, "inconclusive": self.inconclusive,
                "worst_ratio": None if w is None else (w if np.isfinite(w) else "inf"),
                "worst": self.worst, "ties": self.ties, "provided": sorted(self.provided),
                "clause_status": self.clause_status, "failure": self.failure,
                "duration_s": round(self.duration, 3)}


@dataclass
class RunResult:
    backend: BackendInfo
    settings: Settings
    results: list
    clauses: dict
    started: str
    duration: float
    oracle_version: str = ORACLE_VERSION

    @property
    def failed_clauses(self) -> list[str]:
        from .report import clause_table
        return [c for c, row in clause_table(self.results, self.clauses).items() if row["status"] == "fail"]

    @property
    def exit_status(self) -> int:
        return 1 if self.failed_clauses else 0


class _Falsified(AssertionError):
    """Raised inside the hypothesis property when a scene fails the check."""


def _safe_evaluate(check: Check, ctx: Context, scene: Scene) -> Verdict:
    try:
        return check.evaluate(ctx, scene)
    except Exception as exc:      # an oracle-side error: report it as a failure, never hide it
        tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
        return Verdict([problem("oracle", f"evaluating {check.name} raised "
                                          f"{type(exc).__name__}: {exc} ({tb})")])


def run_check(ctx: Context, check: Check, settings: Settings) -> CheckResult:
    """Run one check (see module docstring)."""
    t0 = time.perf_counter()
    why = check.unavailable(ctx)
    if why is not None:
        return CheckResult(check, why[0], why[1])
    state = {"n": 0, "worst": None, "fail": None, "provided": set(), "ties": {},
             "inconclusive": 0, "why": ""}

    def prop(scene):
        scene = scene.rounded(ctx.dtype)
        state["n"] += 1
        v = _safe_evaluate(check, ctx, scene)
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
    try:
        test()
    except _Falsified:
        result.status = "fail"
    except Unsatisfiable:
        result.status = "fail"
        result.failure = {"message": f"no example could be judged: every scene held more near-ties "
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
    if result.status == "fail" and state["fail"] is not None:
        _record_failure(ctx, check, settings, result, *state["fail"])
    for cid, outs in check.clause_outputs.items():
        if result.status == "pass" and not (set(outs) & result.provided):
            result.clause_status[cid] = "not provided"
    result.duration = time.perf_counter() - t0
    return result


def _record_failure(ctx, check, settings, result, scene, verdict):
    stats = None
    if settings.shrink:
        scene, verdict, stats = shrink(lambda s: check.evaluate(ctx, s.rounded(ctx.dtype)), scene,
                                       verdict, settings.shrink_budget)
    w = verdict.worst
    result.worst_ratio = float(w.ratio) if w is not None else float("inf")
    failure = {"message": verdict.message(), "comparison": w.to_json() if w is not None else None,
               "scene": scene.summary(), "parameters": scene_parameters(scene),
               "shrink": stats.to_json() if stats else None, "reproducer": None, "replay": None}
    if settings.report_dir:
        path = Path(settings.report_dir) / "failures" / f"{check.name}.npz"
        save_scene(path, scene, check=check.name, clauses=",".join(check.clauses),
                   backend=ctx.backend.spec, message=verdict.message()[:2000])
        failure["reproducer"] = str(path)
        failure["replay"] = f"python -m oracle replay {path} --backend {ctx.backend.spec or '<module:object>'}"
    result.failure = failure


def run(backend: BackendInfo, settings: Settings | None = None, checks=None, progress=None) -> RunResult:
    """Run ``checks`` (default: all, or those citing ``settings.clauses``) against ``backend``."""
    settings = settings or Settings()
    clauses = load_clauses()
    if checks is None:
        checks = CHECKS
        if settings.clauses:
            want = set(settings.clauses)
            checks = [c for c in CHECKS if want & set(c.clauses)]
    ctx = Context(backend)
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    t0 = time.perf_counter()
    results = []
    for check in checks:
        r = run_check(ctx, check, settings)
        results.append(r)
        if progress is not None:
            progress(r)
    return RunResult(backend, settings, results, clauses, started, time.perf_counter() - t0)


def calibrate(backend: BackendInfo, settings: Settings | None = None, progress=None,
              checks=None) -> dict:
    """Measure, without judging, how far the backend is from the reference (ORC-03).

    Runs every applicable check for ``settings.max_examples`` examples each (no check stops at a
    failure) with :data:`oracle.compare.RECORDER` switched on, and returns, per tolerance row, the
    worst element error (as the atol the row would need at its rtol) and, for gradient rows, the
    worst relative L2 error, 1 - cosine and magnitude ratio.
    """
    from . import compare
    from . import tolerances as tl

    settings = settings or Settings()
    ctx = Context(backend)
    keys = {}
    for key, tol in tl.TABLE.items():
        keys.setdefault(id(tol), []).append(key)
    worst: dict = {}
    compare.RECORDER = []
    try:
        for check in (CHECKS if checks is None else checks):
            if check.unavailable(ctx) is not None or check.kind in ("errors", "reference"):
                continue
            n = max(1, int(round(settings.max_examples * check.examples)))

            def make_prop(check):
                def prop(scene):
                    _safe_evaluate(check, ctx, scene.rounded(ctx.dtype))
                return prop
            prop = make_prop(check)

            test = hsettings(max_examples=n, deadline=None, database=None, phases=[Phase.generate],
                             suppress_health_check=list(HealthCheck), verbosity=Verbosity.quiet)(
                given(scene=check.scenes(ctx))(prop))
            hseed(settings.seed)(test)()
            for tol, label, m in compare.RECORDER:
                k = (keys.get(id(tol), [("?", label, ctx.dtype)])[0][0], label)
                row = worst.setdefault(k, {"atol_needed": 0.0, "rel_l2": 0.0, "one_minus_cosine": 0.0,
                                           "mag_ratio": 1.0, "flips": 0, "in_band": 0, "n": 0,
                                           "tol": tol, "worst_check": ""})
                row["n"] += 1
                row.setdefault("by_check", {})
                bc = row["by_check"].setdefault(check.name, {})
                for f in ("atol_needed", "rel_l2"):
                    if f in m:
                        bc[f] = max(bc.get(f, 0.0), m[f])
                for f in ("atol_needed", "rel_l2", "one_minus_cosine"):
                    if f in m and m[f] > row[f]:
                        row[f] = m[f]
                        if f == "atol_needed":
                            row["worst_check"] = check.name
                if "mag_ratio" in m:
                    row["mag_ratio"] = min(row["mag_ratio"], m["mag_ratio"])
                row["flips"] += m.get("flips", 0)
                row["in_band"] += m.get("in_band", 0)
            compare.RECORDER.clear()
            if progress is not None:
                progress(check)
    finally:
        compare.RECORDER = None
    return worst
