"""Minimal failing scene: greedy delta debugging after hypothesis' own shrinking (ORC-06).

Hypothesis shrinks what it drew (it drops list elements, moves floats toward simple values).
This pass then works on the scene itself, keeping a change only while the check *still fails
for the same output*:

1. remove Gaussians: chunks of half, a quarter, ... then single Gaussians (ddmin);
2. crop the image from each side (the principal point moves with the crop: cx -= x0, cy -= y0);
3. simplify the config: SH degree 0 with K = 1, black background, no opacity_scale;

repeating until nothing changes or the evaluation budget is spent.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import refgs

from .evaluate import Verdict
from .protocol import Scene

#: most check evaluations one shrink may spend
DEFAULT_BUDGET = 150


@dataclass
class ShrinkStats:
    evaluations: int = 0
    n_before: int = 0
    n_after: int = 0
    size_before: tuple = (0, 0)
    size_after: tuple = (0, 0)

    def to_json(self) -> dict:
        return {"evaluations": self.evaluations, "gaussians": [self.n_before, self.n_after],
                "image": [list(self.size_before), list(self.size_after)]}


def _failing_outputs(v: Verdict) -> set:
    return {c.output for c in v.comparisons if not c.ok}


def crop(scene: Scene, x0: int, y0: int, width: int, height: int) -> Scene:
    """The sub-image [x0, x0+width) x [y0, y0+height): same pose, principal point moved (CNV-08)."""
    c = scene.camera
    K = np.array(c.K, dtype=np.float64)
    K[0, 2] -= x0
    K[1, 2] -= y0
    return scene.with_camera(refgs.Camera(np.asarray(c.world_to_camera), K, int(width), int(height)))


def simplify_sh(scene: Scene) -> Scene:
    g = scene.gaussians
    s = scene.with_gaussians(g.replace(sh=np.ascontiguousarray(g.sh[:, :1, :])))
    return s.with_config(sh_degree=0)


def shrink(evaluate, scene: Scene, verdict: Verdict, budget: int = DEFAULT_BUDGET):
    """Smallest scene found on which ``evaluate(scene) -> Verdict`` still fails the same way.

    Returns ``(scene, verdict, ShrinkStats)``.
    """
    target = _failing_outputs(verdict)
    stats = ShrinkStats(n_before=scene.n, size_before=(scene.camera.width, scene.camera.height))
    best = (scene, verdict)

    def still_fails(s: Scene):
        if stats.evaluations >= budget:
            return None
        stats.evaluations += 1
        try:
            v = evaluate(s)
        except Exception:                     # a scene the reference rejects is not a candidate
            return None
        return v if (not v.ok and not v.inconclusive and _failing_outputs(v) & target) else None

    changed = True
    while changed and stats.evaluations < budget:
        changed = False
        # 1. remove Gaussians (ddmin over index chunks)
        keep = np.arange(best[0].n)
        chunk = max(1, keep.size // 2)
        while keep.size > 0 and stats.evaluations < budget:
            removed_any = False
            for start in range(0, keep.size, chunk):
                trial = np.delete(keep, np.arange(start, min(start + chunk, keep.size)))
                cand = best[0].subset(trial.astype(np.int64))
                v = still_fails(cand)
                if v is not None:
                    best = (cand, v)
                    keep = np.arange(best[0].n)
                    removed_any = changed = True
                    break
            if not removed_any:
                if chunk == 1:
                    break
                chunk = max(1, chunk // 2)
        # 2. crop each side as far as it still fails (halving steps)
        for side in ("left", "right", "top", "bottom"):
            step = (best[0].camera.width if side in ("left", "right") else best[0].camera.height) // 2
            while step >= 1 and stats.evaluations < budget:
                c = best[0].camera
                W, H = c.width, c.height
                if side in ("left", "right") and W - step < 1 or side in ("top", "bottom") and H - step < 1:
                    step //= 2
                    continue
                box = {"left": (step, 0, W - step, H), "right": (0, 0, W - step, H),
                       "top": (0, step, W, H - step), "bottom": (0, 0, W, H - step)}[side]
                trial = crop(best[0], *box)
                v = still_fails(trial)
                if v is not None:
                    best = (trial, v)
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
            v = still_fails(simpler)
            if v is not None:
                best = (simpler, v)
                changed = True
    stats.n_after = best[0].n
    stats.size_after = (best[0].camera.width, best[0].camera.height)
    return best[0], best[1], stats

