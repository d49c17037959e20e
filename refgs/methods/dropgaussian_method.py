"""DropGaussian as a training method: its hook in the trainer (clauses DG-01, DG-02).

The idea itself (drop rate r(t), keep mask, opacity compensation) is refgs/methods/dropgaussian.py;
this module only plugs it into the loop through ``before_render`` (refgs/train/hooks.py):

    before_render   opacity_scale = keep / (1 - r(t)) for every Gaussian, rendered with theta (DG-01)

Nothing else changes: the gradients are the plain ones and test renders take no scale.
"""
from __future__ import annotations

import numpy as np

from ..train.hooks import Method, RenderRequest
from .dropgaussian import R_MAX, drop_opacity_scale


class DropGaussianMethod(Method):
    """DropGaussian (DG-01): random drop with opacity compensation during training only.

    r_max  the largest drop rate, reached at t = T (``--drop-r-max``, default R_MAX = 0.2)
    """

    name = "dropgaussian"

    def __init__(self, r_max: float = R_MAX):
        self.r_max = float(r_max)

    def params_dict(self) -> dict:
        return {"r_max": self.r_max}

    def opacity_scale(self, trainer, t: int, rng: np.random.Generator) -> np.ndarray:
        """(N,) factors keep / (1 - r(t)) from N uniforms of ``rng`` (DG-01)."""
        scale, _ = drop_opacity_scale(trainer.n, t, trainer.cfg.iters, rng, self.r_max)
        return scale

    def before_render(self, trainer, t, rng):
        return RenderRequest(trainer.gaussians(), opacity_scale=self.opacity_scale(trainer, t, rng))


__all__ = ["DropGaussianMethod"]
