"""The paper's flat-minima method as a training method: its hooks in the trainer (FM-01..FM-11).

The ideas themselves (Scale-Adaptive Perturbation, mask, schedule, clamp, reinit values) are
refgs/methods/flat_minima.py, one function per idea; this module plugs them into the loop through
the hooks of refgs/train/hooks.py.  One iteration t of ``--method fm``:

    before_render    delta, m = sap_offsets(theta, gamma, p, alpha(t), clamp, rng)   (FM-01..FM-04)
                     render theta_hat = theta with means x + delta                    (paper eq. SAP)
    after_backward   grad L(theta_hat) is the gradient of theta: delta is a constant   (FM-05)
    on_densify       the frozen state follows its rows through clone / split / prune    (FM-08)
    frozen_rows      fields reinitialised less than W iterations ago take no step      (FM-08)
    after_step       at t = 1000 k <= T - 1000: reinit scale, rotation, SH above degree 0
                     with their Adam moments, then the opacity reset               (FM-06, FM-07)

With ``dropgaussian=True`` it is the plug-in on DropGaussian (``--method dropgaussian --fm``):
theta_hat is rendered with DropGaussian's opacity scale too (DG-01, DG-02).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import ConfigError
from ..train.densify import reset_opacity
from ..train.hooks import Method, RenderRequest
from .dropgaussian import R_MAX
from .dropgaussian_method import DropGaussianMethod
from .flat_minima import (DEFAULT_CLAMP, GAMMA, ISO_FIXED_FRACTION, P_PERTURB, PERTURB_TARGETS,
                          REINIT_INTERVAL, REINIT_WINDOW, NoiseShape, is_reinit_iteration,
                          magnitude_schedule, perturb_other, perturb_probability, reinit_values,
                          sap_offsets)

#: The SH coefficients that keep training through a reinit: the DC term, k = 0 (FM-07).
SH_KEPT = 1


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
            raise ConfigError(f"--fm-perturb: expected one of {PERTURB_TARGETS}, got {self.perturb!r}")

    def to_dict(self) -> dict:
        return asdict(self)


def reinit_field_rows(rows: np.ndarray, n_sh: int) -> dict:
    """The entries FM-07 reinitialises and FM-08 freezes, on the Gaussians ``rows`` (N,) bool:
    name -> a bool array broadcasting against the parameter (whole rows of log-scales and
    rotations; SH coefficients k >= 1 of the rows, shape (N, n_sh, 1)).  The form that
    ``Adam.step`` (``frozen_rows``) and ``Adam.reset_rows`` take."""
    sh = np.zeros((len(rows), n_sh, 1), bool)
    sh[:, SH_KEPT:, 0] = rows[:, None]
    return {"log_scales": rows, "quats": rows, "sh": sh}


class FlatMinimaMethod(Method):
    """The paper's method (FM-01..FM-11); with ``dropgaussian=True`` the plug-in on DropGaussian.

    config  FlatMinimaConfig;  r_max  DropGaussian's largest drop rate (plug-in only)
    State: ``frozen_until`` (N,) int64, per Gaussian the last iteration of its frozen window
    (checkpointed as ``method/frozen_until``); ``last_mask`` (N,) bool, the perturbation mask of
    the latest ``before_render``.
    """

    name = "fm"

    def __init__(self, config: FlatMinimaConfig = FlatMinimaConfig(), dropgaussian: bool = False,
                 r_max: float = R_MAX):
        self.config = config
        self.drop = DropGaussianMethod(r_max) if dropgaussian else None
        if dropgaussian:
            self.name = "dropgaussian+fm"
        self.frozen_until = np.zeros(0, np.int64)
        self.last_mask = np.zeros(0, bool)
        #: noise "iso_fixed": the standard deviation (None until ``setup`` resolves the default)
        self.fixed_sigma = config.noise_fixed_sigma

    def params_dict(self) -> dict:
        d = self.config.to_dict()
        if self.drop is not None:
            d.update(self.drop.params_dict())
        return d

    def setup(self, trainer) -> None:
        if self.frozen_until.size != trainer.n:
            self.frozen_until = np.zeros(trainer.n, np.int64)
        if self.fixed_sigma is None:       # FM-01: half the densification size threshold
            self.fixed_sigma = ISO_FIXED_FRACTION * trainer.cfg.densify.percent_dense * trainer.extent

    # FM-01..FM-04: theta_hat (paper eqs. SAP, stochastic, schedule)
    def before_render(self, trainer, t, rng):
        cfg = self.config
        total = trainer.cfg.iters
        alpha = magnitude_schedule(t, total) if cfg.schedule else 1.0
        # FM-11: the mixed loss perturbs every Gaussian (p = 1) and adds a clean render
        p = 1.0 if cfg.mixed_loss else perturb_probability(t, total, cfg.p, cfg.p_ramp)
        g = trainer.gaussians()
        # theta is checked where theta_hat is rendered (refgs' backends validate every field; a
        # non-finite theta gives a non-finite theta_hat, and the trainer stops on a non-finite loss)
        offsets, mask = sap_offsets(g, gamma=cfg.gamma, p=p, alpha=alpha, clamp=cfg.clamp, rng=rng,
                                    noise=NoiseShape(cfg.noise, self.fixed_sigma), validate=False)
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
    def after_backward(self, trainer, t, request, grads):
        if not self.config.mixed_loss:
            return grads.params()
        # FM-11: 0.5 grad L(theta_hat) + 0.5 grad L(theta); statistics stay the perturbed ones
        clean_cfg = trainer.current_render_config
        _, clean, _, _ = trainer.loss_and_grads(trainer.gaussians(), trainer.current_view, clean_cfg, t)
        pert, cl = grads.params(), clean.params()
        return {k: 0.5 * pert[k] + 0.5 * cl[k] for k in pert}

    # FM-08: children of frozen Gaussians inherit the frozen state
    def on_densify(self, trainer, remap) -> None:
        self.frozen_until = self.frozen_until[np.asarray(remap.parent, np.int64)] \
            if self.frozen_until.size else np.zeros(trainer.n, np.int64)

    # FM-08: the frozen window
    def frozen_rows(self, trainer, t):
        if not self.config.reinit:
            return None
        rows = self.frozen_until >= t
        if not rows.any():
            return None
        return reinit_field_rows(rows, trainer.params["sh"].shape[1])

    # FM-06/FM-07: periodic reinitialisation (after the densification of the same iteration)
    def after_step(self, trainer, t, rng):
        cfg = self.config
        if not cfg.reinit or not is_reinit_iteration(t, trainer.cfg.iters, cfg.reinit_interval):
            return
        p = trainer.params
        vals = reinit_values(p["means"], p["sh"].shape[1], p["means"].dtype)
        p["log_scales"][...] = vals["log_scales"]
        p["quats"][...] = vals["quats"]
        p["sh"][:, SH_KEPT:, :] = 0
        every = np.ones(trainer.n, bool)             # FM-07: all current Gaussians
        for name, rows in reinit_field_rows(every, p["sh"].shape[1]).items():
            trainer.adam.reset_rows(name, rows)
        self.frozen_until = np.full(trainer.n, t + cfg.reinit_window, np.int64)
        # "opacity is reset at each interval following the standard mechanism" (TRN-06); once:
        # not again when the standard schedule already reset it at this iteration
        dcfg = trainer.cfg.densify
        standard = t < dcfg.resolved_until(trainer.cfg.iters) and t % dcfg.opacity_reset_interval == 0
        if cfg.reinit_opacity_reset and not standard:
            reset_opacity(p, trainer.adam)

    def state_arrays(self) -> dict:
        return {"frozen_until": self.frozen_until}

    def load_state_arrays(self, arrays: dict) -> None:
        if "frozen_until" in arrays:
            self.frozen_until = np.asarray(arrays["frozen_until"], np.int64)


__all__ = ["FlatMinimaConfig", "FlatMinimaMethod", "reinit_field_rows"]
