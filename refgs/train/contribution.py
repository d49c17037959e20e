"""How much each Gaussian contributes to the training views, and what a render costs (TRN-14).

A Gaussian's *contribution* to a view is the sum over pixels of its blending weight
$w_i(p) = \\alpha_i(p) T_i(p)$ (RAS-05): the share of the pixel's colour it paints. Summed over the
training views it is the global significance of LightGaussian / Mini-Splatting and the score of
Speedy-Splat's pruning; a Gaussian with a contribution near 0 can go without changing a render.

It is read through any backend's backward, exactly: the composited colour is linear in each
Gaussian's colour, $\\partial C(p) / \\partial c_i = w_i(p)$, so with every colour set to 1 (SH degree
0, DC coefficient $(1 - 0.5) / C_0$: no colour clamp is active) and the image cotangent 1 in the
red channel and 0 elsewhere, the gradient of the DC coefficient is $C_0 \\sum_p w_i(p)$. The
weights do not depend on the colours, so this is the contribution of the Gaussians as they are.

The *fragments* of a render are its pixel-Gaussian pairs, $\\sum_p$ ``n_contrib(p)`` (the Gaussians
a pixel's front-to-back loop visits up to its last contributor, RAS-06): the work of the
compositing forward and backward.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import SH_C0, SH_COLOR_OFFSET
from ..types import Gaussians, RenderConfig

#: The DC coefficient that makes every colour exactly 1: (1 - SH_COLOR_OFFSET) / SH_C0 (SH-03).
WHITE_DC = (1.0 - SH_COLOR_OFFSET) / SH_C0
#: The shares of the total contribution reported by ``carried_by`` (docs/compact.md).
CARRY_SHARES = (0.9, 0.99, 0.999)


@dataclass(frozen=True)
class Contribution:
    """Per-Gaussian contribution over some views, and their cost.

    weight     (N,) float64  sum over the views' pixels of alpha_i T_i
    fragments  (V,) int      pixel-Gaussian pairs of each view's render (sum of n_contrib)
    pixels     (V,) int      pixels of each view
    """

    weight: np.ndarray
    fragments: np.ndarray
    pixels: np.ndarray

    def carried_by(self, shares=CARRY_SHARES) -> dict[float, int]:
        """share -> the fewest Gaussians whose contributions sum to at least that share of the
        total (the largest first)."""
        w = np.sort(self.weight)[::-1]
        total = float(w.sum())
        cum = np.cumsum(w)
        return {s: int(min(np.searchsorted(cum, s * total) + 1, len(w))) if total > 0 else 0
                for s in shares}


def white_gaussians(g: Gaussians) -> Gaussians:
    """``g`` with every colour 1: SH degree 0, DC = WHITE_DC (geometry and opacity unchanged)."""
    sh = np.zeros((len(g), 1, 3), dtype=g.sh.dtype)
    sh[:, 0, :] = WHITE_DC
    return Gaussians(means=g.means, log_scales=g.log_scales, quats=g.quats,
                     opacity_logits=g.opacity_logits, sh=sh)


def contributions(backend, gaussians: Gaussians, cameras, profile: str = "inria") -> Contribution:
    """The contribution of each of ``gaussians`` summed over ``cameras`` (refgs.Camera list),
    rendered by ``backend`` (an object with ``render`` / ``render_backward``, refgs.backends)."""
    white = white_gaussians(gaussians)
    weight = np.zeros(len(gaussians))
    fragments, pixels = [], []
    cfg = RenderConfig(profile=profile, sh_degree=0)
    for cam in cameras:
        out = backend.render(white, cam, cfg)
        v_image = np.zeros(out.image.shape, dtype=out.image.dtype)
        v_image[..., 0] = 1
        grads = backend.render_backward(out, v_image)
        weight += np.asarray(grads.sh[:, 0, 0], dtype=np.float64) / SH_C0
        fragments.append(int(np.sum(out.n_contrib, dtype=np.int64)))
        pixels.append(int(cam.width) * int(cam.height))
    return Contribution(weight=weight, fragments=np.array(fragments), pixels=np.array(pixels))


__all__ = ["Contribution", "contributions", "white_gaussians", "WHITE_DC", "CARRY_SHARES"]
