"""The paper's flat-minima method: Scale-Adaptive Perturbation, stochastic masks, schedule, clamp,
periodic reinitialisation.  Reads like the paper's Method section: one function per idea.

Spec: docs/spec/method.md (clauses FM-01..FM-11).  Paper: "Flat Minima Optimization" section,
eq. (SAP)  x_i' = x_i + delta_i,  delta_i ~ N(0, gamma^2 Sigma_i),  Sigma_i = R_i S_i S_i^T R_i^T;
eq. (stochastic)  perturbed with probability p;  eq. (schedule)  x_i' = x_i + alpha(t) delta_i,
alpha(t) = t / T;  Experimental Setup: p_max = 0.3, gamma = 2, reinit every 1000 iterations for
W = 100 iterations, displacement clamped to the Gaussian's scale.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..covariance import normalize_quats, quat_to_rotmat
from ..render import validate_gaussians
from ..types import Gaussians

#: Experimental Setup: "perturbation coefficient gamma = 2"  [FM-01]
GAMMA = 2.0
#: Experimental Setup: "perturbation probability p_max = 0.3"  [FM-02]
P_PERTURB = 0.3
#: Experimental Setup: reinitialise "every 1,000 iterations"  [FM-06]
REINIT_INTERVAL = 1000
#: Experimental Setup: "for W = 100 iterations"  [FM-06]
REINIT_WINDOW = 100

#: The readings of "the displacement does not exceed the corresponding Gaussian's scale" [FM-04].
#: With l = R^T delta the displacement in the Gaussian's principal frame:
#:   "axis"      per principal axis, per component: l_k <- clip(l_k, -s_k, s_k)   (default)
#:   "box"       per principal axis, direction-preserving: l <- l / max(1, max_k |l_k| / s_k)
#:   "ellipsoid" inside the 1-sigma ellipsoid, direction-preserving: l <- l / max(1, ||l / s||)
#:   "norm"      Euclidean length at most ||s||_2, direction-preserving
#:   "none"      no clamp
#: Every reading guarantees ||delta|| <= ||s||_2 (tests/test_flat_minima.py::test_clamp_bounds).
CLAMP_MODES = ("axis", "box", "ellipsoid", "norm", "none")
DEFAULT_CLAMP = "axis"


def magnitude_schedule(t: int, total: int) -> float:
    """alpha(t) = t / T (paper eq. schedule) [FM-03]; 0 at t = 0, 1 at t = T."""
    if total <= 0:
        raise ValueError(f"--iters: expected a positive number of iterations, got {total}")
    return float(t) / float(total)


def perturb_probability(t: int, total: int, p: float = P_PERTURB, ramp: bool = False) -> float:
    """p, constant by default; with ``ramp`` p(t) = p t / T (DropGaussian's form) [FM-02].

    The paper calls the value p_max but its text and equations ramp only the magnitude
    (alpha(t) multiplies delta, p stays the probability), so constant p is the default.
    """
    return p * magnitude_schedule(t, total) if ramp else p


def clamp_displacement(local: np.ndarray, scales: np.ndarray, mode: str = DEFAULT_CLAMP) -> np.ndarray:
    """Clamp displacements given in each Gaussian's principal frame [FM-04].

    local (N,3) = R^T delta, scales (N,3) = s  ->  clamped (N,3); see CLAMP_MODES.
    """
    if mode == "none":
        return local
    if mode == "axis":
        return np.clip(local, -scales, scales)
    if mode == "box":
        f = np.max(np.abs(local) / scales, axis=-1, keepdims=True)
    elif mode == "ellipsoid":
        f = np.sqrt(np.sum((local / scales) ** 2, axis=-1, keepdims=True))
    elif mode == "norm":
        f = np.linalg.norm(local, axis=-1, keepdims=True) / np.linalg.norm(scales, axis=-1, keepdims=True)
    else:
        raise ValueError(f"clamp: expected one of {CLAMP_MODES}, got {mode!r}")
    return local / np.maximum(f, 1)


@dataclass(frozen=True)
class NoiseShape:
    """Which axes scale the noise (the paper's ablation 'noise distribution') [FM-01].

    "anisotropic" (default): gamma R S z.  "iso_max" / "iso_mean": gamma s* R z with s* the
    largest / mean axis.  "iso_fixed": gamma * fixed_sigma * z for every Gaussian.
    """

    kind: str = "anisotropic"
    fixed_sigma: float = 0.0


#: "iso_fixed" noise: a fixed standard deviation of half the densification size threshold
#: (percent_dense x scene extent, the clone/split boundary of TRN-05), the paper's ablation row
#: "isotropic, fixed".  [FM-01]
ISO_FIXED_FRACTION = 0.5


def sap_offsets(gaussians: Gaussians, gamma: float = GAMMA, p: float = P_PERTURB, alpha: float = 1.0,
                clamp: bool | str = True, rng: np.random.Generator | None = None,
                noise: NoiseShape = NoiseShape(), validate: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """Scale-Adaptive Perturbation offsets, masked, scheduled and clamped [FM-01..FM-04].

    gaussians  N Gaussians (validated like ``render``)
    gamma      perturbation coefficient (delta ~ N(0, gamma^2 Sigma))
    p          probability that a Gaussian is perturbed
    alpha      magnitude schedule value alpha(t), applied before the clamp
    clamp      True (= the default reading "axis"), False (= "none") or a CLAMP_MODES name
    rng        an explicitly seeded numpy Generator (required)
    validate   check ``gaussians`` like ``render`` (API-03); False only for a caller that renders
               theta_hat = theta + offsets right after (the trainer's FM hook), where the same
               checks run on theta_hat, whose fields are theta's or non-finite where theta's are
    Returns ``(offsets (N,3) in the Gaussians' dtype, mask (N,) bool)``; offsets are exactly
    zero where mask is False.  Draw order: the mask (N uniforms), then z (N x 3 normals), so the
    same seed gives the same offsets.
    """
    if validate:
        validate_gaussians(gaussians)
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng: expected an explicitly seeded numpy.random.Generator, "
                         f"got {type(rng).__name__}")
    if not (np.isfinite(gamma) and gamma >= 0):
        raise ValueError(f"gamma: expected a finite value >= 0, got {gamma}")
    if not 0 <= p <= 1:
        raise ValueError(f"p: expected a probability in [0, 1], got {p}")
    if not (np.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha: expected a finite value >= 0, got {alpha}")
    mode = DEFAULT_CLAMP if clamp is True else ("none" if clamp is False else clamp)
    if mode not in CLAMP_MODES:
        raise ValueError(f"clamp: expected True, False or one of {CLAMP_MODES}, got {clamp!r}")
    dt = gaussians.means.dtype
    n = len(gaussians)
    mask = rng.random(n) < p
    z = rng.standard_normal((n, 3))
    rows = np.flatnonzero(mask)       # only the perturbed Gaussians need R and S (a fraction p)
    z = z[rows]
    q_unit, _, _ = normalize_quats(gaussians.quats[rows].astype(np.float64))
    R = quat_to_rotmat(q_unit)
    s = np.exp(gaussians.log_scales[rows].astype(np.float64))
    if noise.kind == "anisotropic":
        sigma = s
    elif noise.kind == "iso_max":
        sigma = np.repeat(s.max(axis=-1, keepdims=True), 3, axis=-1)
    elif noise.kind == "iso_mean":
        sigma = np.repeat(s.mean(axis=-1, keepdims=True), 3, axis=-1)
    elif noise.kind == "iso_fixed":
        sigma = np.full_like(s, noise.fixed_sigma)
    else:
        raise ValueError(f"noise: expected anisotropic, iso_max, iso_mean or iso_fixed, got {noise.kind!r}")
    local = alpha * gamma * sigma * z                 # delta = alpha gamma R S z, in the principal frame
    local = clamp_displacement(local, s, mode)        # clamp after the schedule (FM-04)
    offsets = np.zeros((n, 3), dt)
    offsets[rows] = np.einsum("nij,nj->ni", R, local)     # rounded to dt on assignment
    return offsets, mask


def clipped_fraction(alpha: float, mode: str, gamma: float = GAMMA, n: int = 200_000, seed: int = 0,
                     scales=(1.0, 1.0, 1.0)) -> float:
    """Monte-Carlo fraction of Gaussians (for "axis": of axes) the clamp changes at ``alpha`` [FM-04].

    Never depends on the rotation.  For "axis", "box" and "ellipsoid" it does not depend on the
    scales either (they clamp in units of s); for "axis" it equals P(|alpha gamma z| > 1) =
    erfc(1 / (sqrt(2) alpha gamma)) per axis.  For "norm" (bound ||s||, not per axis) it depends
    on the axis ratios: ``scales`` gives them (default isotropic).
    """
    rng = np.random.default_rng(seed)
    s = np.broadcast_to(np.asarray(scales, np.float64), (n, 3))
    local = alpha * gamma * s * rng.standard_normal((n, 3))
    if mode == "axis":
        return float(np.mean(np.abs(local) > s))
    clamped = clamp_displacement(local, s, mode)
    return float(np.mean(np.any(clamped != local, axis=-1)))


# ---------------------------------------------------------------------------------------------
# Ablation: which parameter is perturbed [FM-10]
# ---------------------------------------------------------------------------------------------

#: The perturbed-parameter variants of the paper's ablation table ("position" is the method).
PERTURB_TARGETS = ("position", "rotation", "scale", "opacity", "position+scale")
#: Our choice (the paper gives no magnitudes for its ablation variants): standard deviations per
#: unit of gamma, scheduled by alpha(t) like delta.  Rotation: angles (radians) about the three
#: principal axes, 0.05 rad ~ 2.9 deg; scale: log-scale offsets, i.e. proportional to each axis
#: (s_k exp(eps_k) ~ s_k (1 + eps_k)), 0.1 ~ 10 %; opacity: logit offsets, 0.1.  [FM-10]
ROTATION_SIGMA = 0.05
SCALE_SIGMA = 0.1
OPACITY_SIGMA = 0.1


def axis_angle_quats(omega: np.ndarray) -> np.ndarray:
    """Unit quaternions (N,4) (w,x,y,z) of rotations by the vectors omega (N,3) (angle = |omega|)."""
    angle = np.linalg.norm(omega, axis=-1)
    half = 0.5 * angle
    # sin(half)/angle, with its limit 1/2 at angle 0
    k = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half)[:, None], omega * k[:, None]], axis=-1)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a * b of (N,4) quaternions (w,x,y,z)."""
    aw, ax, ay, az = (a[:, i] for i in range(4))
    bw, bx, by, bz = (b[:, i] for i in range(4))
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def perturb_other(gaussians: Gaussians, target: str, gamma: float, alpha: float, mask: np.ndarray,
                  rng: np.random.Generator) -> dict:
    """The non-position perturbations of the ablation [FM-10], on the rows of ``mask``.

    Returns the replaced fields of theta_hat (a dict for ``Gaussians.replace``):
      "rotation": q' = q * q(omega), omega ~ N(0, (alpha gamma ROTATION_SIGMA)^2 I): a rotation
                  about the Gaussian's own principal axes (right multiplication)
      "scale":    log s' = log s + alpha gamma SCALE_SIGMA z (proportional to each axis)
      "opacity":  logit' = logit + alpha gamma OPACITY_SIGMA z
    Draws N x 3 (rotation, scale) or N (opacity) normals after the caller's mask and offsets.
    """
    n = len(gaussians)
    dt = gaussians.means.dtype
    if target == "rotation":
        omega = alpha * gamma * ROTATION_SIGMA * rng.standard_normal((n, 3))
        q = gaussians.quats.astype(np.float64)
        q2 = quat_multiply(q, axis_angle_quats(omega))
        return {"quats": np.where(mask[:, None], q2, q).astype(dt)}
    if target == "scale":
        eps = alpha * gamma * SCALE_SIGMA * rng.standard_normal((n, 3))
        return {"log_scales": np.where(mask[:, None], gaussians.log_scales + eps, gaussians.log_scales).astype(dt)}
    if target == "opacity":
        eps = alpha * gamma * OPACITY_SIGMA * rng.standard_normal(n)
        return {"opacity_logits": np.where(mask, gaussians.opacity_logits + eps,
                                           gaussians.opacity_logits).astype(dt)}
    raise ValueError(f"perturb: expected one of {PERTURB_TARGETS}, got {target!r}")


# ---------------------------------------------------------------------------------------------
# Periodic reinitialisation [FM-06..FM-08]
# ---------------------------------------------------------------------------------------------

def is_reinit_iteration(t: int, total: int, interval: int = REINIT_INTERVAL) -> bool:
    """Reinit at t = interval * k, k >= 1, for t <= T - interval [FM-06]."""
    return t > 0 and t % interval == 0 and t <= total - interval


def reinit_values(means: np.ndarray, n_sh: int, dtype) -> dict:
    """The SfM-style initial state of scale, rotation and higher-order SH for the current
    positions [FM-07]: log-scales from the 3-NN mean squared distance (as the initial cloud),
    identity rotation (1, 0, 0, 0), zero SH coefficients above degree 0.
    Returns {"log_scales": (N,3), "quats": (N,4), "sh_rest": (N, n_sh - 1, 3)}."""
    from ..data.init import knn_log_scales
    n = means.shape[0]
    log_s = knn_log_scales(np.asarray(means, np.float64)).astype(dtype)
    if log_s.ndim == 1:
        log_s = np.repeat(log_s[:, None], 3, axis=-1)
    quats = np.zeros((n, 4), dtype)
    quats[:, 0] = 1
    return {"log_scales": log_s, "quats": quats, "sh_rest": np.zeros((n, max(n_sh - 1, 0), 3), dtype)}
