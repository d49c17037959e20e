"""The paper's method and DropGaussian as trainer Methods (clauses FM-05..FM-08, DG-01, DG-02).

The trainer (refgs/train/trainer.py) calls these hooks; the ideas themselves live in
flat_minima.py and dropgaussian.py.  One iteration of ``fm``:

    render_request   delta, mask = sap_offsets(theta, gamma, p, alpha(t), clamp, rng)   (FM-01..04)
                     render theta_hat = theta with means + delta
    param_gradients  grad L(theta_hat) applied to theta: the position gradient at x + delta is
                     the gradient of x (delta is a constant), other fields unchanged      (FM-05)
    frozen_rows      fields reinitialised less than W iterations ago take no step       (FM-08)
    after_densify    frozen state follows rows through clone / split / prune            (FM-08)
    after_step       at t = 1000 k <= T - 1000: reinit scale, rotation, SH rest; opacity reset (FM-06/07)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..train.densify import reset_opacity
from ..train.trainer import Method, RenderRequest, register_method
from .dropgaussian import R_MAX, drop_opacity_scale
from .flat_minima import (DEFAULT_CLAMP, GAMMA, ISO_FIXED_FRACTION, P_PERTURB, PERTURB_TARGETS,
                          REINIT_INTERVAL, REINIT_WINDOW, NoiseShape, is_reinit_iteration,
                          magnitude_schedule, perturb_other, perturb_probability, reinit_values,
                          sap_offsets)

#: Parameter fields reinitialised and frozen by FM-07/FM-08 (SH: only coefficients k >= 1).
REINIT_FIELDS = ("log_scales", "quats", "sh")


@dataclass(frozen=True)
class FlatMinimaConfig:
    """Every parameter of the method, recorded in config.json under these names (DG-02)."""

    gamma: float = GAMMA
    p: float = P_PERTURB
    p_ramp: bool = False
    schedule: bool = True
    clamp: str = DEFAULT_CLAMP
    noise: str = "anisotropic"
    #: for noise "iso_fixed": the standard deviation; None = ISO_FIXED_FRACTION x the
    #: densification size threshold (percent_dense x extent), resolved when training starts
    noise_fixed_sigma: float | None = None
    reinit: bool = True
    reinit_interval: int = REINIT_INTERVAL
    reinit_window: int = REINIT_WINDOW
    reinit_opacity_reset: bool = True
    #: ablation (FM-10): which parameter theta_hat perturbs
    perturb: str = "position"
    #: ablation (FM-11): RWP-style mixed loss instead of the stochastic per-Gaussian mask
    mixed_loss: bool = False

    def __post_init__(self):
        if self.perturb not in PERTURB_TARGETS:
            raise ValueError(f"--fm-perturb: expected one of {PERTURB_TARGETS}, got {self.perturb!r}")

    def to_dict(self) -> dict:
        return asdict(self)


class DropGaussianMethod(Method):
    """DropGaussian (DG-01): random drop with opacity compensation during training only."""

    name = "dropgaussian"

    def __init__(self, r_max: float = R_MAX):
        self.r_max = float(r_max)

    def params_dict(self) -> dict:
        return {"drop_r_max": self.r_max}

    def opacity_scale(self, trainer, t: int, rng: np.random.Generator):
        scale, _ = drop_opacity_scale(trainer.n, t, trainer.cfg.iters, rng, self.r_max)
        return scale

    def render_request(self, trainer, t, rng):
        return RenderRequest(trainer.gaussians(), opacity_scale=self.opacity_scale(trainer, t, rng))


class FlatMinimaMethod(Method):
    """The paper's method (FM-01..FM-08); with ``dropgaussian=True`` the plug-in on DropGaussian."""

    name = "fm"

    def __init__(self, config: FlatMinimaConfig = FlatMinimaConfig(), dropgaussian: bool = False,
                 r_max: float = R_MAX):
        self.config = config
        self.drop = DropGaussianMethod(r_max) if dropgaussian else None
        if dropgaussian:
            self.name = "dropgaussian+fm"
        self.frozen_until = np.zeros(0, np.int64)   # per Gaussian: last iteration without a step
        self.last_mask = np.zeros(0, bool)
        #: noise "iso_fixed": the standard deviation (None until ``setup`` resolves the default)
        self.fixed_sigma = config.noise_fixed_sigma

    def params_dict(self) -> dict:
        d = {f"fm_{k}": v for k, v in self.config.to_dict().items()}
        if self.drop is not None:
            d.update(self.drop.params_dict())
        return d

    def setup(self, trainer) -> None:
        if self.frozen_until.size != trainer.n:
            self.frozen_until = np.zeros(trainer.n, np.int64)
        if self.fixed_sigma is None:       # FM-01: half the densification size threshold
            self.fixed_sigma = ISO_FIXED_FRACTION * trainer.cfg.densify.percent_dense * trainer.extent

    # FM-01..FM-04: theta_hat
    def render_request(self, trainer, t, rng):
        cfg = self.config
        total = trainer.cfg.iters
        alpha = magnitude_schedule(t, total) if cfg.schedule else 1.0
        # FM-11: the mixed loss perturbs every Gaussian (p = 1) and adds a clean render
        p = 1.0 if cfg.mixed_loss else perturb_probability(t, total, cfg.p, cfg.p_ramp)
        g = trainer.gaussians()
        offsets, mask = sap_offsets(g, gamma=cfg.gamma, p=p, alpha=alpha, clamp=cfg.clamp, rng=rng,
                                    noise=NoiseShape(cfg.noise, self.fixed_sigma))
        self.last_mask = mask
        changes = {}
        if cfg.perturb in ("position", "position+scale"):
            changes["means"] = g.means + offsets
        if cfg.perturb != "position":      # FM-10 ablation: the same mask, other fields
            other = "scale" if cfg.perturb == "position+scale" else cfg.perturb
            changes.update(perturb_other(g, other, cfg.gamma, alpha, mask, rng))
        scale = self.drop.opacity_scale(trainer, t, rng) if self.drop is not None else None
        return RenderRequest(g.replace(**changes), opacity_scale=scale,
                             extra={"offsets": offsets, "mask": mask})

    # FM-05: the gradient at theta_hat is applied to theta (delta is a constant)
    def param_gradients(self, trainer, t, request, grads):
        if not self.config.mixed_loss:
            return grads.params()
        # FM-11: 0.5 grad L(theta_hat) + 0.5 grad L(theta); statistics stay the perturbed ones
        clean_cfg = trainer.current_render_config
        _, clean, _, _ = trainer.loss_and_grads(trainer.gaussians(), trainer.current_view, clean_cfg, t)
        pert, cl = grads.params(), clean.params()
        return {k: 0.5 * pert[k] + 0.5 * cl[k] for k in pert}

    # FM-08: frozen window
    def frozen_rows(self, trainer, t):
        if not self.config.reinit:
            return None
        rows = self.frozen_until >= t
        if not rows.any():
            return None
        sh_mask = np.zeros(trainer.params["sh"].shape[:2] + (1,), bool)
        sh_mask[:, 1:, 0] = rows[:, None]            # DC colour keeps training
        return {"log_scales": rows, "quats": rows, "sh": sh_mask}

    def after_densify(self, trainer, remap) -> None:
        self.frozen_until = self.frozen_until[np.asarray(remap.parent, np.int64)] \
            if self.frozen_until.size else np.zeros(trainer.n, np.int64)

    # FM-06/FM-07: periodic reinitialisation (after densify of the same iteration)
    def after_step(self, trainer, t, rng):
        cfg = self.config
        if not cfg.reinit or not is_reinit_iteration(t, trainer.cfg.iters, cfg.reinit_interval):
            return
        p = trainer.params
        vals = reinit_values(p["means"], p["sh"].shape[1], p["means"].dtype)
        p["log_scales"][...] = vals["log_scales"]
        p["quats"][...] = vals["quats"]
        p["sh"][:, 1:, :] = 0
        for name in REINIT_FIELDS:
            if name == "sh":
                trainer.adam.m["sh"][:, 1:, :] = 0
                trainer.adam.v["sh"][:, 1:, :] = 0
            else:
                trainer.adam.zero(name)
        self.frozen_until = np.full(trainer.n, t + cfg.reinit_window, np.int64)
        # "opacity is reset at each interval following the standard mechanism"; skip if the
        # standard schedule already reset it at this iteration
        dcfg = trainer.cfg.densify
        standard = t < dcfg.resolved_until(trainer.cfg.iters) and t % dcfg.opacity_reset_interval == 0
        if cfg.reinit_opacity_reset and not standard:
            reset_opacity(p, trainer.adam)

    def state_arrays(self) -> dict:
        return {"frozen_until": self.frozen_until}

    def load_state_arrays(self, arrays: dict) -> None:
        if "frozen_until" in arrays:
            self.frozen_until = np.asarray(arrays["frozen_until"], np.int64)


def make_method(name: str, fm: bool = False, fm_config: FlatMinimaConfig = FlatMinimaConfig(),
                r_max: float = R_MAX) -> Method:
    """--method {3dgs, fm, dropgaussian} [--fm] (DG-02)."""
    if name == "fm":
        return FlatMinimaMethod(fm_config)
    if name == "dropgaussian":
        return FlatMinimaMethod(fm_config, dropgaussian=True, r_max=r_max) if fm else DropGaussianMethod(r_max)
    if name == "3dgs":
        return FlatMinimaMethod(fm_config) if fm else Method()
    raise ValueError(f"--method: expected 3dgs, fm or dropgaussian, got {name!r}")


#: method_params keys (config.json) -> FlatMinimaConfig fields
_FM_KEYS = tuple(FlatMinimaConfig.__dataclass_fields__)


def _factory(name: str):
    def build(fm: bool = False, r_max: float = R_MAX, **fm_params) -> Method:
        unknown = set(fm_params) - set(_FM_KEYS)
        if unknown:
            raise ValueError(f"method parameters: unknown {sorted(unknown)}; expected {list(_FM_KEYS)}")
        return make_method(name, fm=fm, fm_config=FlatMinimaConfig(**fm_params), r_max=r_max)
    return build


for _name in ("3dgs", "fm", "dropgaussian"):
    register_method(_name, _factory(_name))
