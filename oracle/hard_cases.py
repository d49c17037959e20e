"""The hard-case catalogue as scene builders, one per HARD-01 .. HARD-13 (docs/spec/hard_cases.md).

Each builder is ``build(rng, caps) -> Case``: a small scene (<= 40 Gaussians, <= 64 x 48
pixels) reproducing the situation of the bug report the clause cites, inside the backend's
declared capabilities ``caps`` (a strategies.Capabilities: its profile, SH degree, camera model,
background; ORC-02).  The oracle draws the seed
with hypothesis (:func:`hard_case_scenes`), renders with the backend and the reference, and
compares forward and backward (oracle/checks.py, one check per HARD id).

    HARD_CASES["HARD-07"].build(np.random.default_rng(0), Capabilities("inria")) -> Case
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from hypothesis import strategies as st

import refgs
from refgs.constants import PROFILES

from .protocol import Case
from .strategies import SH_COEFFS, Capabilities, random_quats, random_sh, unproject

W, H = 48, 32


def _camera(rng, *, w=W, h=H, fx=None, off_centre=False, tilt=0.3) -> refgs.Camera:
    """A camera about 4 units from the origin looking at it, slightly tilted."""
    fx = float(rng.uniform(35, 60)) if fx is None else fx
    eye = np.array([0.0, 0.0, -4.0]) + rng.normal(0, tilt, 3)
    cx = w / 2 + (rng.uniform(-0.15, 0.15) * w if off_centre else 0.0)
    cy = h / 2 + (rng.uniform(-0.15, 0.15) * h if off_centre else 0.0)
    return refgs.Camera.look_at(eye, rng.normal(0, 0.1, 3), fx=fx, width=w, height=h, cx=cx, cy=cy)


def _gaussians(rng, cam, uv, z, log_scales, logits, quats=None, k=SH_COEFFS) -> refgs.Gaussians:
    uv = np.asarray(uv, float).reshape(-1, 2)
    n = uv.shape[0]
    means = unproject(cam, uv[:, 0], uv[:, 1], np.broadcast_to(np.asarray(z, float), (n,)))
    ls = np.broadcast_to(np.asarray(log_scales, float), (n, 3)).copy()
    lg = np.broadcast_to(np.asarray(logits, float), (n,)).copy()
    q = random_quats(rng, n) if quats is None else np.asarray(quats, float)
    return refgs.Gaussians(means, ls, q, lg, random_sh(rng, n, k))


def _scene(g, cam, caps: Capabilities, rng, label, **cfg) -> Case:
    """The case, inside ``caps``: at most its SH degree and coefficients (SH-01), a black
    background where it declares none (the random draws are the same either way)."""
    cfg.setdefault("sh_degree", 3 if g.sh.shape[1] >= 16 else 0)
    cfg["sh_degree"] = min(cfg["sh_degree"], caps.max_sh_degree)
    if not caps.background:
        cfg["background"] = (0.0, 0.0, 0.0)
    return Case(caps.fit_sh(g), cam, refgs.RenderConfig(profile=caps.profile, **cfg),
                seed=int(rng.integers(2**31)), label=label)


def _limit_fraction(cam, profile, side=1.0) -> float:
    """Image fraction (u/W) of the frustum clamp limit on the +x (side=1) or -x side (PRF-02)."""
    p = PROFILES[profile]
    tan_x = cam.width / (2 * cam.fx)
    if p.frustum_symmetric:
        lim = (1 + p.frustum_margin) * tan_x
        u = cam.cx + side * cam.fx * lim
    else:
        lim = ((cam.width - cam.cx) / cam.fx if side > 0 else cam.cx / cam.fx) + p.frustum_margin * tan_x
        u = cam.cx + side * cam.fx * lim
    return u / cam.width


def hard01(rng, caps):
    """Gaussians clamped by the frustum (|t_x/t_z| beyond the limit, one with t_y clamped) whose
    tails reach the image: the depth gradient under the clamp (#75, PRJ-07)."""
    cam = _camera(rng)
    n = int(rng.integers(2, 7))
    side = rng.choice([-1.0, 1.0], n)
    u = np.array([_limit_fraction(cam, caps.profile, s) for s in side]) * cam.width
    u += side * rng.uniform(2, 25, n)
    v = rng.uniform(0.2, 0.8, n) * cam.height
    v[0] = cam.height * (1.9 if rng.random() < 0.5 else -0.9)       # t_y clamped too
    g = _gaussians(rng, cam, np.stack([u, v], -1), rng.uniform(2.5, 5, n),
                   rng.uniform(-0.3, 0.6, (n, 3)), rng.uniform(0, 4, n))
    return _scene(g, cam, caps, rng, "HARD-01 frustum clamp")


def hard02(rng, caps):
    """Needles (one axis 1e3..1e6 x the others) crossing the frustum limits (gsplat PR #977)."""
    cam = _camera(rng)
    n = int(rng.integers(2, 8))
    side = rng.choice([-1.0, 1.0], n)
    u = np.array([_limit_fraction(cam, caps.profile, s) for s in side]) * cam.width
    u += side * rng.uniform(-8, 8, n)
    base = rng.uniform(-6, -4, n)
    ls = np.repeat(base[:, None], 3, 1)
    ls[np.arange(n), rng.integers(0, 3, n)] += np.log(10.0 ** rng.uniform(3, 6, n))
    ls = np.minimum(ls, 1.5)
    g = _gaussians(rng, cam, np.stack([u, rng.uniform(0.2, 0.8, n) * cam.height], -1),
                   rng.uniform(2.5, 5, n), ls, rng.uniform(0, 3, n))
    return _scene(g, cam, caps, rng, "HARD-02 off-screen needles")


def hard03(rng, caps):
    """Anisotropic Gaussians rotated in screen space (b != 0): the off-diagonal conic gradient
    (#551; RAS-08)."""
    cam = _camera(rng)
    n = int(rng.integers(3, 9))
    ls = np.stack([rng.uniform(-2.2, -1.2, n), rng.uniform(-3.8, -2.8, n), rng.uniform(-3, -2, n)], -1)
    ang = rng.uniform(0.3, 1.2, n) * rng.choice([-1, 1], n)
    # rotation by ``ang`` about the camera's optical axis, written in world coordinates
    axis = cam.rotation.T @ np.array([0, 0, 1.0])
    quats = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis[None, :]], -1)
    g = _gaussians(rng, cam, rng.uniform(0.2, 0.8, (n, 2)) * [cam.width, cam.height],
                   rng.uniform(3, 5, n), ls, rng.uniform(0, 3, n), quats=quats)
    return _scene(g, cam, caps, rng, "HARD-03 conic off-diagonal")


def hard04(rng, caps):
    """One Gaussian, isotropic or anisotropic (gsplat #91: compare every gradient, in pixels)."""
    cam = _camera(rng)
    iso = rng.random() < 0.5
    ls = np.full(3, rng.uniform(-2.5, -1.5)) if iso else rng.uniform(-3.5, -1.2, 3)
    g = _gaussians(rng, cam, rng.uniform(0.3, 0.7, (1, 2)) * [cam.width, cam.height],
                   rng.uniform(3, 5), ls, rng.uniform(-1, 4))
    return _scene(g, cam, caps, rng, "HARD-04 single Gaussian")


def _focal_ratio(rng, caps) -> float:
    """fy / fx of HARD-05: 0.95 .. 1.05, or 1 for a one-focal-length camera model (CNV-03)."""
    r = float(rng.uniform(0.95, 1.05))
    return 1.0 if caps.camera_model == "simple_pinhole" else r


def hard05(rng, caps):
    """A real-camera-like geometry: off-centre principal point, fx != fy, tilted pose, depths
    2..20 (gsplat #157 / PR #172)."""
    fx = float(rng.uniform(40, 70))
    eye = rng.normal(0, 1.0, 3) + [0.5, -0.3, -5.0]
    cam = refgs.Camera.look_at(eye, rng.normal(0, 0.5, 3), up=(0.1, -1.0, 0.2), fx=fx,
                               fy=fx * _focal_ratio(rng, caps), width=64, height=48,
                               cx=32 + rng.uniform(-6, 6), cy=24 + rng.uniform(-5, 5))
    n = int(rng.integers(10, 36))
    z = np.exp(rng.uniform(np.log(2), np.log(20), n))
    g = _gaussians(rng, cam, rng.uniform(-0.1, 1.1, (n, 2)) * [64, 48], z,
                   np.log(z)[:, None] - 4.0 + rng.uniform(-1, 1, (n, 3)), rng.uniform(-1, 4, n))
    return _scene(g, cam, caps, rng, "HARD-05 real camera geometry")


def hard06(rng, caps):
    """Tiny scales (1e-4 .. 1e-7, one axis or all) and quaternion norms down to 1e-30 (#248)."""
    cam = _camera(rng)
    n = int(rng.integers(3, 12))
    ls = np.log(10.0 ** rng.uniform(-7, -4, (n, 3)))
    one_axis = rng.random(n) < 0.5
    ls[one_axis] = np.log(10.0 ** rng.uniform(-2, -1, (int(one_axis.sum()), 3)))
    ls[one_axis, rng.integers(0, 3, int(one_axis.sum()))] = np.log(1e-7)
    q = random_quats(rng, n) * (10.0 ** rng.uniform(-30, 0, n))[:, None]
    g = _gaussians(rng, cam, rng.uniform(0.1, 0.9, (n, 2)) * [cam.width, cam.height],
                   rng.uniform(2, 6, n), ls, rng.uniform(0, 5, n), quats=q)
    return _scene(g, cam, caps, rng, "HARD-06 tiny scales and quaternions")


def hard07(rng, caps):
    """A stack of 2..20 nearly opaque Gaussians (logit up to 20) on one pixel (gsplat #556)."""
    cam = _camera(rng)
    k = int(rng.integers(2, 21))
    px = rng.uniform(0.3, 0.7, 2) * [cam.width, cam.height]
    uv = px + rng.normal(0, 0.8, (k, 2))
    g = _gaussians(rng, cam, uv, 2.0 + np.cumsum(rng.uniform(0.05, 0.3, k)),
                   rng.uniform(-2.4, -1.6, (k, 3)), rng.uniform(4, 20, k))
    return _scene(g, cam, caps, rng, "HARD-07 opaque stack")


def hard08(rng, caps):
    """Early termination with skipped fragments in between and Gaussians behind the stop: which
    fragment is the last contributor (#1130; n_contrib, RAS-06)."""
    cam = _camera(rng)
    k = int(rng.integers(3, 10))
    px = rng.uniform(0.35, 0.65, 2) * [cam.width, cam.height]
    z = 2.0 + np.cumsum(rng.uniform(0.05, 0.3, 3 * k))
    logits = np.where(np.arange(3 * k) % 3 == 1, -7.0, rng.uniform(3, 8, 3 * k))   # faint: < 1/255
    uv = px + rng.normal(0, 1.5, (3 * k, 2))
    g = _gaussians(rng, cam, uv, z, rng.uniform(-2.6, -1.8, (3 * k, 3)), logits)
    return _scene(g, cam, caps, rng, "HARD-08 last contributor")


def hard09(rng, caps):
    """Opacity reset to 0.01: Gaussians of several sizes, some with the mean on a pixel corner;
    their opacity gradients must exist exactly where the reference's do (gsplat #1011)."""
    cam = _camera(rng)
    n = int(rng.integers(3, 10))
    uv = rng.uniform(0.2, 0.8, (n, 2)) * [cam.width, cam.height]
    corner = rng.random(n) < 0.5
    uv[corner] = np.round(uv[corner])
    z = rng.uniform(3, 5, n)
    ls = np.log(10.0 ** rng.uniform(-6, -1, n))[:, None] + rng.uniform(-0.2, 0.2, (n, 3))
    logit = np.log(0.01 / 0.99)
    g = _gaussians(rng, cam, uv, z, ls, np.full(n, logit))
    return _scene(g, cam, caps, rng, "HARD-09 support collapse after reset")


def hard10(rng, caps):
    """White or random background, gradients with respect to it (#86)."""
    cam = _camera(rng)
    n = int(rng.integers(3, 15))
    g = _gaussians(rng, cam, rng.uniform(0.1, 0.9, (n, 2)) * [cam.width, cam.height],
                   rng.uniform(2.5, 6, n), rng.uniform(-2.8, -1.5, (n, 3)), rng.uniform(-1, 3, n))
    bg = (1.0, 1.0, 1.0) if rng.random() < 0.5 else tuple(float(x) for x in rng.uniform(0, 1, 3))
    return _scene(g, cam, caps, rng, "HARD-10 background gradient", background=bg)


#: largest log-scale of HARD-11's splats: s = e^6 = 400 world units covers every tile of any
#: oracle image many times over; much larger values overflow float32 intermediates (det^2 of
#: the 2D covariance passes 3.4e38 near log-scale 8.5) without testing anything more here
HARD11_MAX_LOG_SCALE = 6.0


def hard11(rng, caps):
    """Huge splats (log-scale up to 6: 400 world units) and Gaussians just beyond the near plane,
    covering every tile (#28, gsplat #464)."""
    cam = _camera(rng)
    near = PROFILES[caps.profile].near
    n = int(rng.integers(2, 8))
    z = np.where(rng.random(n) < 0.5, near * rng.uniform(1.05, 2.0, n), rng.uniform(2, 6, n))
    close = (z < 1)[:, None]
    ls = np.where(close, np.log(near) + rng.uniform(-1, 1, (n, 3)), rng.uniform(1, HARD11_MAX_LOG_SCALE, (n, 3)))
    g = _gaussians(rng, cam, rng.uniform(0.2, 0.8, (n, 2)) * [cam.width, cam.height], z, ls,
                   rng.uniform(-3, 1, n))
    return _scene(g, cam, caps, rng, "HARD-11 huge splats")


def hard12(rng, caps):
    """An empty scene (K in {1, 4, 16}) or one where every Gaussian is culled (#472, API-06)."""
    cam = _camera(rng)
    k = int(rng.choice([1, 4, 16]))
    deg = {1: 0, 4: 1, 16: 3}[k]
    if rng.random() < 0.5:
        g = refgs.Gaussians.empty(k)
    else:
        n = int(rng.integers(1, 6))
        g = _gaussians(rng, cam, rng.uniform(0.2, 0.8, (n, 2)) * [cam.width, cam.height],
                       rng.uniform(2, 4, n), -2.0, 2.0, k=k)
        g = g.replace(means=2 * cam.center - g.means)            # mirrored behind the camera
    bg = tuple(float(x) for x in rng.uniform(0, 1, 3))
    return _scene(g, cam, caps, rng, "HARD-12 empty / all culled", sh_degree=deg, background=bg)


def hard13(rng, caps):
    """Discs (one scale 1e-8 of the others) turned through the exactly edge-on angle (Unity #14)."""
    cam = _camera(rng, tilt=0.0)
    n = int(rng.integers(2, 8))
    ls = np.full((n, 3), rng.uniform(-2.0, -1.2))
    ls[:, 2] += np.log(1e-8)
    # disc normal (local z) perpendicular to the view ray: rotate local z onto world x-ish
    ang = rng.uniform(-0.02, 0.02, n) + np.pi / 2
    axis = cam.rotation.T @ np.array([0, 1.0, 0])
    quats = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis[None]], -1)
    g = _gaussians(rng, cam, rng.uniform(0.3, 0.7, (n, 2)) * [cam.width, cam.height],
                   rng.uniform(3, 5, n), ls, rng.uniform(0, 4, n), quats=quats)
    return _scene(g, cam, caps, rng, "HARD-13 rank-1 edge-on")


@dataclass(frozen=True)
class HardCase:
    id: str
    build: Callable[[np.random.Generator, Capabilities], Case]

    @property
    def doc(self) -> str:
        """The builder's docstring, whitespace collapsed (shown in reports)."""
        return " ".join((self.build.__doc__ or "").split())


HARD_CASES: dict[str, HardCase] = {
    f"HARD-{i:02d}": HardCase(f"HARD-{i:02d}", fn) for i, fn in enumerate(
        (hard01, hard02, hard03, hard04, hard05, hard06, hard07, hard08, hard09, hard10, hard11,
         hard12, hard13), start=1)}


def hard_case_strategy(case_id: str, caps: Capabilities) -> st.SearchStrategy[Case]:
    """Hypothesis strategy of cases of one hard case (the seed is what is drawn)."""
    case = HARD_CASES[case_id]
    return st.integers(0, 2**32 - 1).map(lambda s: case.build(np.random.default_rng(s), caps))


__all__ = ["HARD_CASES", "HardCase", "hard_case_strategy"]
