"""Densification strategies: the paper's protocol and the compact one, side by side (TRN-04..TRN-06,
TRN-14).

A strategy decides, at each iteration t, which image the trainer fits (``training_view``) and how
the set of Gaussians changes (``densification``: statistics, densify-and-prune, opacity reset, and
for the compact strategy contribution pruning and a budget). ``Trainer.step`` calls both; the
methods' hooks (refgs.train.hooks) see the same rows moving through ``Method.on_densify``.

    PaperStrategy     TRN-04..TRN-06 exactly as 3DGS / DropGaussian run them (the default)
    CompactStrategy   TRN-14: the same, plus a Gaussian budget, contribution pruning during
                      densification (soft) and once when it ends (hard), and a rendering
                      resolution schedule
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from ..errors import ConfigError
from ..types import Gaussians
from .contribution import contributions
from .densify import densify_and_prune, prune_rows, reset_opacity

#: Parameter tensors, all replaced when rows change (no Adam step that iteration, as 3DGS).
ALL_TENSORS = Gaussians.FIELDS


@dataclass(frozen=True)
class CompactConfig:
    """Settings of the compact strategy (TRN-14); the defaults change nothing.

    budget               at most this many Gaussians: densification keeps its best-scoring
                         candidates (largest mean screen-space gradient) up to it; None: no cap
    prune_fraction       soft pruning: every ``prune_every`` iterations while densifying (t > the
                         densification start), remove this fraction of the Gaussians, those with
                         the least contribution over the training views (refgs.train.contribution)
    prune_every          iterations between soft prunings
    final_prune_fraction hard pruning: once, at the iteration densification ends (its ``until``,
                         when that is before T), remove this fraction the same way
    resolution_schedule  ((start, factor), ...): from iteration start * T on, fit the training
                         images downsampled by the integer ``factor`` (intrinsics scaled alike);
                         starts increasing from 0, factors >= 1; () = full resolution throughout
    """

    budget: int | None = None
    prune_fraction: float = 0.0
    prune_every: int = 500
    final_prune_fraction: float = 0.0
    resolution_schedule: tuple = ()

    def validate(self) -> "CompactConfig":
        if self.budget is not None and (isinstance(self.budget, bool) or not isinstance(
                self.budget, (int, np.integer)) or self.budget < 1):
            raise ConfigError(f"--budget: expected a positive integer, got {self.budget!r}")
        for name in ("prune_fraction", "final_prune_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v < 1.0):
                raise ConfigError(f"--{name.replace('_', '-')}: expected a fraction in [0, 1), got {v!r}")
        if isinstance(self.prune_every, bool) or not isinstance(self.prune_every, (int, np.integer)) \
                or self.prune_every < 1:
            raise ConfigError(f"--prune-every: expected a positive integer, got {self.prune_every!r}")
        sched = self.resolution_schedule
        starts = [s for s, _ in sched]
        if sched and (starts[0] != 0 or any(b <= a for a, b in zip(starts, starts[1:]))
                      or not all(0 <= s < 1 for s in starts)
                      or not all(isinstance(f, (int, np.integer)) and f >= 1 for _, f in sched)):
            raise ConfigError("--resolution-schedule: expected START:FACTOR,... with starts rising "
                              f"from 0 (fractions of T below 1) and integer factors >= 1, got {sched!r}")
        return self

    def factor_at(self, t: int, iters: int) -> int:
        """The downsampling factor of iteration t (1-based) of a run of ``iters`` iterations."""
        factor = 1
        for start, f in self.resolution_schedule:
            if t > start * iters:
                factor = int(f)
        return factor

    def to_dict(self) -> dict:
        d = asdict(self)
        d["resolution_schedule"] = [[float(s), int(f)] for s, f in self.resolution_schedule]
        return d

    @staticmethod
    def from_dict(d: dict) -> "CompactConfig":
        unknown = set(d) - {f.name for f in fields(CompactConfig)}
        if unknown:
            raise ConfigError(f"config.json: unknown compact settings {sorted(unknown)}")
        kw = dict(d)
        kw["resolution_schedule"] = tuple((float(s), int(f)) for s, f in kw.get("resolution_schedule", ()))
        return CompactConfig(**kw)


#: ``refgs train --compact`` (grid key ``compact = true``): the compact settings, the fraction of
#: T at which densification ends (then the hard pruning), and the SH degree.  Its parts:
#: DashGaussian's coarse-to-fine resolution, Speedy-Splat's soft and hard pruning, Taming 3DGS'
#: budget.  The values were chosen by the fern 3-view FM trial runs of docs/compact.md (seed 0,
#: one run each): full resolution for the last tenth keeps the PSNR of 0.7 T; the budget of
#: 25,000 halves the work of the half-resolution phase, where most of the loop's time goes.
COMPACT_PRESET = {
    "compact": {"budget": 25000, "prune_fraction": 0.1, "prune_every": 500,
                "final_prune_fraction": 0.3,
                "resolution_schedule": ((0.0, 4), (0.3, 2), (0.9, 1))},
    "densify_until": 0.6,
    "sh_degree": 3,
}


def compact_label(compact: dict | None) -> str:
    """The suffix of a method label for a run's ``compact`` settings (as in config.json): "" for
    the paper's strategy, "+compact" plus the settings that differ from CompactConfig's defaults,
    e.g. ``+compact(budget=40000,resolution_schedule=0:2/0.5:1)``."""
    if compact is None:
        return ""
    default = CompactConfig().to_dict()
    parts = []
    for key in sorted(compact):
        value = compact[key]
        if value == default.get(key):
            continue
        if key == "resolution_schedule":
            value = "/".join(f"{s:g}:{int(f)}" for s, f in value)
        parts.append(f"{key}={value}")
    return "+compact" + (f"({','.join(parts)})" if parts else "")


def parse_resolution_schedule(text: str) -> tuple:
    """``"0:4,0.3:2,0.6:1"`` -> ((0.0, 4), (0.3, 2), (0.6, 1)) (the command line's form)."""
    try:
        pairs = tuple((float(a), int(b)) for a, b in (item.split(":") for item in text.split(",")))
    except ValueError:
        raise ConfigError(f"--resolution-schedule: expected START:FACTOR,... (e.g. 0:4,0.3:2,0.6:1), "
                          f"got {text!r}") from None
    return pairs


def downsample_view(view, factor: int):
    """``view`` (refgs.train.trainer.View) at 1/factor resolution: the image averaged over
    factor x factor blocks (cropped at the right and bottom to a multiple of factor), the
    intrinsics fx, fy, cx, cy divided by factor (CNV-08: low-resolution pixel (i, j) is sampled
    at the full-resolution point (factor (j + 0.5), factor (i + 0.5)), the centre of its block)."""
    import dataclasses
    h, w = view.image.shape[0] // factor, view.image.shape[1] // factor
    img = view.image[:h * factor, :w * factor]
    img = img.reshape(h, factor, w, factor, img.shape[2]).mean(axis=(1, 3), dtype=np.float64)
    cam = view.camera
    K = np.array(cam.K, dtype=np.float64)
    K[:2, :] /= factor
    camera = dataclasses.replace(cam, K=K, width=w, height=h)
    return dataclasses.replace(view, camera=camera, image=img.astype(view.image.dtype))


class PaperStrategy:
    """The paper's protocol (TRN-04..TRN-06): full-resolution training views; statistics,
    densify-and-prune at its interval, opacity reset, while t < until."""

    name = "paper"

    def training_view(self, trainer, view, t: int):
        """The view the trainer fits at iteration t (here: the view itself)."""
        return view

    def max_new(self, trainer) -> int | None:
        """At most this many new rows at a densification step (None: no cap)."""
        return None

    def radius_factor(self, trainer, t: int) -> int:
        """Full-resolution pixels per rendered pixel at t (scales the radii statistics)."""
        return 1

    def densification(self, trainer, t: int, grads, out, view) -> set:
        """Adaptive density control of iteration t (TRN-04..TRN-06): accumulate the screen-space
        statistics of the render, densify-and-prune at its interval (then
        ``method.on_densify``), reset opacity at its interval. Returns the names of the
        parameter tensors replaced, which take no Adam step this iteration (as 3DGS)."""
        cfg, dcfg = trainer.cfg, trainer.cfg.densify
        replaced: set = set()
        if t >= dcfg.resolved_until(cfg.iters):
            return replaced
        f = self.radius_factor(trainer, t)
        radii = out.radii if f == 1 else np.asarray(out.radii) * f
        trainer.stats.accumulate(grads.means2d, radii, view.camera.width, view.camera.height)
        if t > dcfg.start and t % dcfg.interval == 0:
            size_active = dcfg.size_prune and t > dcfg.opacity_reset_interval
            remap = densify_and_prune(trainer.params, trainer.stats, trainer.adam, dcfg,
                                      trainer.extent, size_active, trainer.rngs["densify"],
                                      max_new=self.max_new(trainer))
            trainer.method.on_densify(trainer, remap)
            replaced = set(ALL_TENSORS)
        if t % dcfg.opacity_reset_interval == 0 or (cfg.background == "white" and t == dcfg.start):
            reset_opacity(trainer.params, trainer.adam)
            replaced.add("opacity_logits")
        return replaced


class CompactStrategy(PaperStrategy):
    """TRN-14: the paper's densification under a budget, contribution pruning (soft and hard),
    and a rendering resolution schedule (CompactConfig)."""

    name = "compact"

    def __init__(self, cfg: CompactConfig):
        self.cfg = cfg.validate()
        self._views: dict = {}

    def training_view(self, trainer, view, t: int):
        f = self.cfg.factor_at(t, trainer.cfg.iters)
        if f == 1:
            return view
        key = (view.name, f)
        if key not in self._views:
            self._views[key] = downsample_view(view, f)
        return self._views[key]

    def max_new(self, trainer) -> int | None:
        return None if self.cfg.budget is None else self.cfg.budget - trainer.n

    def radius_factor(self, trainer, t: int) -> int:
        return self.cfg.factor_at(t, trainer.cfg.iters)

    def densification(self, trainer, t: int, grads, out, view) -> set:
        replaced = super().densification(trainer, t, grads, out, view)
        dcfg, iters = trainer.cfg.densify, trainer.cfg.iters
        until = dcfg.resolved_until(iters)
        fraction = 0.0
        if self.cfg.prune_fraction > 0 and dcfg.start < t < until and t % self.cfg.prune_every == 0:
            fraction = self.cfg.prune_fraction
        if self.cfg.final_prune_fraction > 0 and t == until < iters:
            fraction = self.cfg.final_prune_fraction
        if fraction > 0:
            self.prune_least(trainer, t, fraction)
            replaced = set(ALL_TENSORS)
        return replaced

    def prune_least(self, trainer, t: int, fraction: float) -> None:
        """Remove ``floor(fraction N)`` Gaussians of least contribution over the training views
        as fitted at t (ties: the lower row goes first), moving the rows of the optimiser, the
        statistics and the method's state (``Method.on_densify``)."""
        cams = [self.training_view(trainer, v, t).camera for v in trainer.train_views]
        weight = contributions(trainer.backend, trainer.gaussians(), cams, trainer.cfg.profile).weight
        keep = np.ones(trainer.n, bool)
        keep[np.argsort(weight, kind="stable")[:int(fraction * trainer.n)]] = False
        remap = prune_rows(trainer.params, trainer.stats, trainer.adam, keep)
        trainer.method.on_densify(trainer, remap)


def make_strategy(compact: CompactConfig | None):
    """The strategy of a run: the paper's when ``compact`` is None (TRN-14)."""
    return PaperStrategy() if compact is None else CompactStrategy(compact)


__all__ = ["CompactConfig", "COMPACT_PRESET", "compact_label", "PaperStrategy", "CompactStrategy", "make_strategy", "downsample_view",
           "parse_resolution_schedule"]
