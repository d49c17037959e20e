"""Calibration: measure, without judging, how far a backend is from the reference (ORC-03).

    worst = calibrate(load_backend("mod:obj"), Settings(max_examples=100))
    python -m oracle calibrate --backend mod:obj --max-examples 100

Rows of oracle/tolerances.py are set from such runs with a 4x margin (never loosened to make a
failing backend pass).  Calibration runs the backend in this process (a backend being
calibrated is one whose author trusts it to run).
"""
from __future__ import annotations

from hypothesis import HealthCheck, Phase, Verbosity, given
from hypothesis import seed as hseed
from hypothesis import settings as hsettings

from .checks import CHECKS
from .evaluate import Context
from .protocol import BackendInfo
from .runner import Settings, safe_evaluate


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
                    safe_evaluate(check, ctx, scene.rounded(ctx.dtype))
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
