"""Adaptive density control: statistics, clone, split, prune, opacity reset (clauses TRN-04..TRN-06).

Source: graphdeco-inria/gaussian-splatting@82bc469 ``train.py`` (gating) and
``scene/gaussian_model.py`` (``add_densification_stats``, ``densify_and_prune``,
``densify_and_clone``, ``densify_and_split``, ``prune_points``, ``reset_opacity``); sparse-view
settings from DCVL-3D/DropGaussian_release@c13da4a (peers.md 1.7, 3.1).

Parameters are a dict of arrays with the names of refgs.Gaussians (means, log_scales, quats,
opacity_logits, sh); every function keeps the Adam moments (refgs.train.adam) on their rows.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.special import expit

from ..covariance import normalize_quats, quat_to_rotmat
from ..errors import ConfigError

#: The rasterizer's backward scales pixel gradients of the 2D mean by 0.5 W and 0.5 H
#: (diff-gaussian-rasterization@59f5f77 backward.cu L460-461: d pixel / d NDC), so the original's
#: densification threshold is in NDC units; refgs' Gradients.means2d is in pixels.  [TRN-04]
NDC_PER_PIXEL_HALF = 0.5
#: Split: each selected Gaussian becomes N = 2 samples (``densify_and_split(..., N=2)``).  [TRN-05]
SPLIT_N = 2
#: Split children get scale / (0.8 N) = scale / 1.6 (``/ (0.8*N)``).  [TRN-05]
SPLIT_SCALE_FACTOR = 0.8
#: Opacity reset caps opacity at 0.01 (``reset_opacity``: ``min(opacity, 0.01)``).  [TRN-06]
OPACITY_RESET_VALUE = 0.01
#: Screen-space pruning in the pipeline's rule: in 3DGS@82bc469 ``densification_postfix`` zeroes
#: ``max_radii2D`` before ``densify_and_prune`` compares it with 20 px, so that test never fires
#: ("upstream"); "accumulated" compares the radii accumulated since the last densification.  [TRN-05]
SCREEN_SIZE_RULES = ("upstream", "accumulated")


@dataclass(frozen=True)
class DensifyConfig:
    """Densification settings (TRN-04..TRN-06); ``until=None`` means the run's T (--iters).

    start           densify when t > start (``densify_from_iter``)
    interval        ... and t % interval == 0 (``densification_interval``)
    until           statistics, densification and opacity resets only while t < until
    grad_threshold  on the mean NDC screen-space gradient norm (``densify_grad_threshold``)
    min_opacity     prune below (``densify_and_prune(..., 0.005, ...)``)
    percent_dense   clone if max scale <= percent_dense * extent, else split
    opacity_reset_interval  reset when t % interval == 0 (``opacity_reset_interval``)
    size_prune      prune big Gaussians once t > opacity_reset_interval (``size_threshold``)
    max_screen_size pixels (``size_threshold = 20``); max_world_size: fraction of the extent (0.1)
    screen_size_rule one of SCREEN_SIZE_RULES
    """

    start: int = 500
    interval: int = 100
    until: int | None = None
    grad_threshold: float = 0.0005
    min_opacity: float = 0.005
    percent_dense: float = 0.01
    opacity_reset_interval: int = 3000
    size_prune: bool = False
    max_screen_size: float = 20.0
    max_world_size: float = 0.1
    screen_size_rule: str = "upstream"

    def resolved_until(self, horizon: int) -> int:
        return int(horizon if self.until is None else min(self.until, horizon))

    def validate(self) -> "DensifyConfig":
        for name in ("start", "interval", "opacity_reset_interval"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < (0 if name == "start" else 1):
                raise ConfigError(f"--densify-{name.replace('_', '-')}: expected a "
                                  f"{'non-negative' if name == 'start' else 'positive'} integer, got {v!r}")
        if self.until is not None and (not isinstance(self.until, (int, np.integer)) or self.until < 0):
            raise ConfigError(f"--densify-until: expected a non-negative integer, got {self.until!r}")
        if not (np.isfinite(self.grad_threshold) and self.grad_threshold >= 0):
            raise ConfigError(f"--densify-grad-threshold: expected >= 0, got {self.grad_threshold!r}")
        if self.screen_size_rule not in SCREEN_SIZE_RULES:
            raise ConfigError(f"--screen-size-rule: expected one of {SCREEN_SIZE_RULES}")
        return self

    def to_dict(self) -> dict:
        return asdict(self)


#: --densify-preset values.  "dropgaussian": DropGaussian_release@c13da4a (threshold 0.0005,
#: until T, no size pruning); "original": 3DGS@82bc469 (threshold 0.0002, until 15000 or T,
#: size pruning after the first opacity reset).  [TRN-04]
DENSIFY_PRESETS = {
    "dropgaussian": DensifyConfig(),
    "original": DensifyConfig(grad_threshold=0.0002, until=15000, size_prune=True),
}


def densify_preset(name: str, **overrides) -> DensifyConfig:
    if name not in DENSIFY_PRESETS:
        raise ConfigError(f"--densify-preset: expected one of {sorted(DENSIFY_PRESETS)}, got {name!r}")
    return replace(DENSIFY_PRESETS[name], **{k: v for k, v in overrides.items() if v is not None})


class DensifyStats:
    """Per-Gaussian statistics since the last densification (TRN-04).

    grad_accum (N,) sum of NDC screen-space gradient norms over iterations where the Gaussian was
    visible (radius > 0); denom (N,) number of those iterations; max_radii (N,) largest radius.
    """

    def __init__(self, n: int):
        self.reset(n)

    def reset(self, n: int) -> None:
        self.grad_accum = np.zeros(n)
        self.denom = np.zeros(n)
        self.max_radii = np.zeros(n)

    def accumulate(self, means2d_grad, radii, width: int, height: int) -> None:
        """Add one iteration (``add_densification_stats`` + the max_radii2D update, TRN-04).

        means2d_grad (N, 2) dL/d 2D mean in pixels (Gradients.means2d); radii (N, 2) ints.
        """
        radii = np.asarray(radii)
        r = np.maximum(radii[:, 0], radii[:, 1])     # = max(axis=1), without the slow short-axis reduction
        vis = r > 0
        g = np.asarray(means2d_grad)
        gx = g[:, 0].astype(np.float64) * (NDC_PER_PIXEL_HALF * width)
        gy = g[:, 1].astype(np.float64) * (NDC_PER_PIXEL_HALF * height)
        # whole-array updates instead of gathers and scatters through ``vis`` (the same values:
        # the sums only ever hold non-negative numbers, so adding 0.0 where not visible is exact)
        self.grad_accum += np.where(vis, np.sqrt(gx * gx + gy * gy), 0.0)  # the L2 norm of the NDC gradient
        self.denom += vis
        np.maximum(self.max_radii, np.where(vis, r, 0), out=self.max_radii)

    def mean_grad(self) -> np.ndarray:
        """accum / denom, 0 where never visible (3DGS sets the NaN of 0/0 to 0)."""
        return np.divide(self.grad_accum, self.denom, out=np.zeros_like(self.grad_accum),
                         where=self.denom > 0)

    def state_arrays(self) -> dict:
        return {"densify/grad_accum": self.grad_accum, "densify/denom": self.denom,
                "densify/max_radii": self.max_radii}

    def load_state_arrays(self, arrays: dict) -> None:
        self.grad_accum = np.array(arrays["densify/grad_accum"], np.float64)
        self.denom = np.array(arrays["densify/denom"], np.float64)
        self.max_radii = np.array(arrays["densify/max_radii"], np.float64)


@dataclass(frozen=True)
class Remap:
    """How rows changed: new row i came from old row ``parent[i]``; ``source[i]`` is that row for
    rows that keep their optimiser state, -1 for new rows (clones, split children)."""

    source: np.ndarray
    parent: np.ndarray
    n_cloned: int
    n_split: int
    n_pruned: int


def _rows(params: dict, index) -> dict:
    return {k: v[index] for k, v in params.items()}


def _cat(a: dict, b: dict) -> dict:
    return {k: np.concatenate([a[k], b[k]], axis=0) for k in a}


def budget_threshold(grads: np.ndarray, threshold: float, room: int) -> float:
    """The densification threshold that admits at most ``room`` candidates (TRN-14 budget): each
    candidate (a clone, or a split: two children for one parent) adds one row, so the best
    ``room`` gradients are kept. Returns ``threshold`` when at most ``room`` reach it, else just
    above the (room+1)-th largest gradient (so ties at the cut are all left out), inf when
    ``room`` <= 0."""
    if room <= 0:
        return float("inf")
    over = grads[grads >= threshold]
    if len(over) <= room:
        return float(threshold)
    cut = np.partition(over, len(over) - room - 1)[len(over) - room - 1]
    return float(np.nextafter(cut, np.inf))


def densify_and_prune(params: dict, stats: DensifyStats, adam, cfg: DensifyConfig, extent: float,
                      size_threshold_active: bool, rng: np.random.Generator,
                      max_new: int | None = None) -> Remap:
    """Clone, split and prune (TRN-05), in 3DGS' order; replaces the arrays of ``params``,
    remaps ``adam`` and resets ``stats``.  Returns the Remap.

    1. g = mean NDC gradient; clone rows with g >= threshold and max scale <= percent_dense *
       extent (copies appended at the end).
    2. split rows (of the enlarged set, clones having g = 0) with g >= threshold and max scale >
       percent_dense * extent: SPLIT_N children x = R n + x, n ~ N(0, diag(s^2)) drawn from
       ``rng`` (children in the original's order: all first samples, then all second), scale
       s / (SPLIT_SCALE_FACTOR * SPLIT_N); the parents are removed.
    3. prune opacity < min_opacity and, if ``size_threshold_active``, max scale > max_world_size
       * extent or (screen_size_rule "accumulated") max radius > max_screen_size.

    ``max_new``: None (the paper's protocol), or at most this many new rows: the threshold of
    steps 1-2 is raised to ``budget_threshold`` (TRN-14).
    """
    n0 = len(params["means"])
    dt = params["means"].dtype
    grads = stats.mean_grad()
    scales = np.exp(params["log_scales"].astype(np.float64))
    smax = scales.max(axis=1)
    dense_limit = cfg.percent_dense * extent
    threshold = cfg.grad_threshold if max_new is None else budget_threshold(
        grads, cfg.grad_threshold, max_new)

    clone = np.flatnonzero((grads >= threshold) & (smax <= dense_limit))
    p1 = _cat(params, _rows(params, clone))
    src1 = np.concatenate([np.arange(n0), clone])
    fresh1 = np.concatenate([np.zeros(n0, bool), np.ones(len(clone), bool)])
    g1 = np.concatenate([grads, np.zeros(len(clone))])
    s1 = np.concatenate([scales, scales[clone]])
    r1 = np.concatenate([stats.max_radii, np.zeros(len(clone))])

    split = (g1 >= threshold) & (s1.max(axis=1) > dense_limit)
    sel = np.flatnonzero(split)
    stds = np.tile(s1[sel], (SPLIT_N, 1))
    samples = rng.standard_normal(stds.shape) * stds
    q_unit = normalize_quats(p1["quats"][sel].astype(np.float64))[0]
    rot = np.tile(quat_to_rotmat(q_unit), (SPLIT_N, 1, 1))
    children = _rows(p1, np.tile(sel, SPLIT_N))
    children["means"] = (np.einsum("nij,nj->ni", rot, samples)
                         + np.tile(p1["means"][sel].astype(np.float64), (SPLIT_N, 1))).astype(dt)
    children["log_scales"] = np.log(stds / (SPLIT_SCALE_FACTOR * SPLIT_N)).astype(dt)
    keep1 = ~split
    p2 = _cat(_rows(p1, keep1), children)
    src2 = np.concatenate([src1[keep1], np.tile(src1[sel], SPLIT_N)])
    fresh2 = np.concatenate([fresh1[keep1], np.ones(SPLIT_N * len(sel), bool)])
    r2 = np.concatenate([r1[keep1], np.zeros(SPLIT_N * len(sel))])

    prune = expit(p2["opacity_logits"].astype(np.float64)) < cfg.min_opacity
    if size_threshold_active:
        prune |= np.exp(p2["log_scales"].astype(np.float64)).max(axis=1) > cfg.max_world_size * extent
        if cfg.screen_size_rule == "accumulated":
            prune |= r2 > cfg.max_screen_size
    keep = ~prune
    params.update(_rows(p2, keep))
    source = np.where(fresh2, -1, src2)[keep]
    adam.remap(source)
    stats.reset(int(keep.sum()))
    return Remap(source=source, parent=src2[keep], n_cloned=len(clone), n_split=len(sel),
                 n_pruned=int(prune.sum()))


def prune_rows(params: dict, stats: DensifyStats, adam, keep: np.ndarray) -> Remap:
    """Keep the rows where ``keep`` (N,) bool is true (TRN-14 contribution pruning): parameters,
    Adam moments and the densification statistics follow their rows (the statistics are not
    reset: pruning is not a densification step)."""
    keep = np.asarray(keep, bool)
    rows = np.flatnonzero(keep)
    params.update(_rows(params, rows))
    adam.remap(rows)
    stats.grad_accum, stats.denom, stats.max_radii = (
        stats.grad_accum[rows], stats.denom[rows], stats.max_radii[rows])
    return Remap(source=rows, parent=rows, n_cloned=0, n_split=0, n_pruned=int((~keep).sum()))


def reset_opacity(params: dict, adam) -> None:
    """opacity <- min(opacity, OPACITY_RESET_VALUE) through the inverse sigmoid; the opacity's
    Adam moments are zeroed, its step count kept (TRN-06)."""
    lo = params["opacity_logits"]
    o = np.minimum(expit(lo.astype(np.float64)), OPACITY_RESET_VALUE)
    params["opacity_logits"] = np.log(o / (1.0 - o)).astype(lo.dtype)
    adam.zero("opacity_logits")


__all__ = ["DensifyConfig", "DensifyStats", "Remap", "DENSIFY_PRESETS", "densify_preset",
           "densify_and_prune", "budget_threshold", "prune_rows", "reset_opacity", "NDC_PER_PIXEL_HALF", "SPLIT_N",
           "SPLIT_SCALE_FACTOR", "OPACITY_RESET_VALUE", "SCREEN_SIZE_RULES"]
