"""Minimal failing case: greedy delta debugging after hypothesis' own shrinking (ORC-06).

Hypothesis shrinks what it drew (it drops list elements, moves floats toward simple values).
This pass then works on the case itself:

1. remove Gaussians: chunks of half, a quarter, ... then single Gaussians (ddmin);
2. crop the image from each side (the principal point moves with the crop: cx -= x0, cy -= y0;
   with ``centred`` both opposite sides at once, so that a centred principal point stays centred);
3. simplify the config: SH degree 0 with K = 1, black background, no opacity_scale;

repeating until nothing changes or the evaluation budget is spent.  A step is kept only if the
failure keeps its *mechanism* (oracle/blame.py ``mechanism``): the check still fails with one of
the original failing outputs and problem sorts -- an exception only with the same type raised at
the same line --, and every remaining Gaussian keeps its depth-culling, frustum-clamp and
visibility flags (cropping moves the clamp limits, which can turn another defect on).  So the
smallest case shows the defect the large one showed, not another one the shrinking happened
upon.  Simplifying the config (no background, no opacity_scale) is kept when the failure stays:
the feature was then not its cause, and oracle/blame.py no longer blames its clause.

When a diagnosis has found the deviations that explain the failure (oracle/diagnose.py), ``keep``
adds its deviation signature (oracle/explain.py ``Signature.keeps``): a step is kept only while
the case still fails without deviations and is still explained by the failure's own deviations,
so each minimal case shows one deviation cleanly rather than another the shrinking happened upon.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import refgs

from .evaluate import Verdict
from .protocol import Case

#: most check evaluations one shrink may spend
DEFAULT_BUDGET = 150


class StopShrinking(Exception):
    """Raised by the ``evaluate`` callback to end shrinking now, keeping the smallest case so far
    (the backend's worker died or ran out of time)."""


@dataclass
class ShrinkStats:
    evaluations: int = 0
    n_before: int = 0
    n_after: int = 0
    size_before: tuple = (0, 0)
    size_after: tuple = (0, 0)
    rejected: int = 0
    stopped: str = ""

    def to_json(self) -> dict:
        return {"evaluations": self.evaluations, "gaussians": [self.n_before, self.n_after],
                "image": [list(self.size_before), list(self.size_after)],
                "rejected_mechanism_changes": self.rejected, "stopped": self.stopped}


def _keys(v: Verdict) -> set:
    """(output, problem sort, origin) of every failing comparison (blame.failure_keys)."""
    return {(c.output, c.kind, c.origin) for c in v.comparisons if not c.ok}


def crop(scene: Case, x0: int, y0: int, width: int, height: int) -> Case:
    """The sub-image [x0, x0+width) x [y0, y0+height): same pose, principal point moved (CNV-08)."""
    c = scene.camera
    K = np.array(c.K, dtype=np.float64)
    K[0, 2] -= x0
    K[1, 2] -= y0
    return scene.with_camera(refgs.Camera(np.asarray(c.world_to_camera), K, int(width), int(height)))


def simplify_sh(scene: Case) -> Case:
    g = scene.gaussians
    s = scene.with_gaussians(g.replace(sh=np.ascontiguousarray(g.sh[:, :1, :])))
    return s.with_config(sh_degree=0)


def _crop_box(case: Case, side: str, step: int):
    W, H = case.camera.width, case.camera.height
    if side in ("left", "right") and W - step < 1 or side in ("top", "bottom") and H - step < 1 \
            or side == "x" and W - 2 * step < 1 or side == "y" and H - 2 * step < 1:
        return None
    return {"left": (step, 0, W - step, H), "right": (0, 0, W - step, H),
            "top": (0, step, W, H - step), "bottom": (0, 0, W, H - step),
            "x": (step, 0, W - 2 * step, H), "y": (0, step, W, H - 2 * step)}[side]


def shrink(evaluate, scene: Case, verdict: Verdict, budget: int = DEFAULT_BUDGET,
           mechanism=None, centred: bool = False, keep=None):
    """Smallest case found on which ``evaluate(case) -> Verdict`` still fails the same way.

    ``mechanism(case, verdict) -> {"keys", "flags" (N, k)}`` (oracle/blame.py), or None to
    require only a common failing output and problem sort.  ``keep(case, verdict) -> bool``: a
    further rule a smaller case must pass (the deviation signature), or None.  Returns
    ``(case, verdict, ShrinkStats)``; ``ShrinkStats.rejected`` counts the cases rejected by
    ``mechanism`` or ``keep``.
    """
    target = _keys(verdict)
    stats = ShrinkStats(n_before=scene.n, size_before=(scene.camera.width, scene.camera.height))
    base = mechanism(scene, verdict) if mechanism is not None else None
    best = (scene, verdict, np.arange(scene.n))       # case, verdict, original index of each row

    def still_fails(s: Case, orig):
        if stats.evaluations >= budget:
            return None
        stats.evaluations += 1
        try:
            v = evaluate(s)
        except StopShrinking:
            raise
        except Exception:                     # a case the reference rejects is not a candidate
            return None
        if v.ok or v.inconclusive or not (_keys(v) & target):
            return None
        if base is not None:
            m = mechanism(s, v)
            if not np.array_equal(m["flags"], base["flags"][orig]):
                stats.rejected += 1
                return None
        if keep is not None and not keep(s, v):
            stats.rejected += 1
            return None
        return v

    try:
        changed = True
        while changed and stats.evaluations < budget:
            changed = False
            # 1. remove Gaussians (ddmin over index chunks)
            chunk = max(1, best[0].n // 2)
            while best[0].n > 0 and stats.evaluations < budget:
                removed_any = False
                for start in range(0, best[0].n, chunk):
                    trial = np.delete(np.arange(best[0].n), np.arange(start, min(start + chunk, best[0].n)))
                    cand = best[0].subset(trial.astype(np.int64))
                    v = still_fails(cand, best[2][trial])
                    if v is not None:
                        best = (cand, v, best[2][trial])
                        removed_any = changed = True
                        break
                if not removed_any:
                    if chunk == 1:
                        break
                    chunk = max(1, chunk // 2)
            # 2. crop each side (or each pair of opposite sides) as far as it still fails
            for side in (("x", "y") if centred else ("left", "right", "top", "bottom")):
                full = best[0].camera.width if side in ("left", "right", "x") else best[0].camera.height
                step = full // (4 if centred else 2)
                while step >= 1 and stats.evaluations < budget:
                    box = _crop_box(best[0], side, step)
                    trial = None if box is None else crop(best[0], *box)
                    v = None if trial is None else still_fails(trial, best[2])
                    if v is not None:
                        best = (trial, v, best[2])
                        changed = True
                    else:
                        step //= 2
            # 3. simpler config
            s = best[0]
            for simpler in (simplify_sh(s) if s.gaussians.sh.shape[1] > 1 else None,
                            s.with_config(background=(0.0, 0.0, 0.0)) if any(s.config.background) else None,
                            s.with_config(opacity_scale=None) if s.config.opacity_scale is not None else None):
                if simpler is None:
                    continue
                v = still_fails(simpler, best[2])
                if v is not None:
                    best = (simpler, v, best[2])
                    changed = True
    except StopShrinking as stop:
        stats.stopped = str(stop)
    stats.n_after = best[0].n
    stats.size_after = (best[0].camera.width, best[0].camera.height)
    return best[0], best[1], stats
