"""Hypothesis strategies for oracle scenes, named by intent (ORC-06).

Scenes are small -- at most ``MAX_GAUSSIANS`` Gaussians, images at most ``MAX_WIDTH x MAX_HEIGHT``
-- so that a full check of one backend runs in well under a minute.  Hypothesis draws the camera
and one seed per Gaussian: its shrinking removes Gaussians and simplifies the camera; each
Gaussian's parameters come from its seed through ``np.random.default_rng`` within the ranges the
strategy names (drawing every float through hypothesis cost more than rendering, and produced
exact boundary values -- a mean exactly on a tile edge -- that are near-ties of no interest).
oracle/shrink.py then removes Gaussians and crops the image further.

Positions are drawn in the camera's terms: a fraction of the image width/height and a depth;
:func:`unproject` turns them into world means.  Every strategy takes the profile name because
"near the near plane" or "off screen" depend on it (PRF-01, PRF-02).

    cameras(...)                       a pinhole camera looking at the origin
    in_front_of(camera, ...)           Gaussians inside (or just around) the view
    straddling_near_plane(camera, p)   depths from 0.3x to 3x the profile's near plane
    off_screen(camera)                 means beyond the frustum clamp, tails reaching the image
    opaque_stack(camera)               2-20 opaque Gaussians along one ray (RAS-05)
    depth_ties(camera)                 Gaussians with exactly equal depths (RAS-02)
    tiny_scales / huge_scales / needle_scales / log_scales / either   log-scale families
    near_degenerate_quaternions(g)     the same Gaussians with quaternion norms 1e-30 .. 1e3
    cases(caps, ...)                   a Case: camera + Gaussians + config + cotangent seed

Every strategy stays inside the backend's declared capabilities (:class:`Capabilities`, ORC-02):
SH degree and coefficients, camera model, principal point, background.  For a backend declaring
everything (the defaults) the draws are exactly those of a capability-free strategy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st

import refgs
from refgs.constants import PROFILES

from .protocol import Case

MAX_GAUSSIANS = 40
MAX_WIDTH, MAX_HEIGHT = 64, 48
#: number of SH coefficients the scenes carry (degree 3); the config picks the active degree
SH_COEFFS = 16
_FLOAT = dict(allow_nan=False, allow_infinity=False, allow_subnormal=False)


def floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, **_FLOAT)


@dataclass(frozen=True)
class Capabilities:
    """What the cases drawn for a backend may contain (its declared capabilities, ORC-02)."""

    profile: str = "inria"
    max_sh_degree: int = 3
    camera_model: str = "pinhole"
    principal_point: bool = True
    background: bool = True

    @classmethod
    def of(cls, backend) -> "Capabilities":
        """From a protocol.BackendInfo."""
        return cls(backend.profile, backend.max_sh_degree, backend.camera_model,
                   backend.supports_principal_point, backend.supports_background)

    @property
    def max_coeffs(self) -> int:
        """SH coefficients per Gaussian a case may carry: (max degree + 1)^2 (SH-01)."""
        return (self.max_sh_degree + 1) ** 2

    def fit_sh(self, g: refgs.Gaussians) -> refgs.Gaussians:
        """``g`` with at most :attr:`max_coeffs` SH coefficients (the first ones: what any degree
        up to the maximum reads, SH-01)."""
        if g.sh.shape[1] <= self.max_coeffs:
            return g
        return g.replace(sh=np.ascontiguousarray(g.sh[:, :self.max_coeffs, :]))

    def admits(self, case: Case) -> str | None:
        """None when ``case`` lies inside these capabilities, else what lies outside."""
        c, cfg = case.camera, case.config
        if str(cfg.profile) != self.profile:
            return f"profile {cfg.profile!r}"
        if case.gaussians.sh.shape[1] > self.max_coeffs:
            return f"{case.gaussians.sh.shape[1]} SH coefficients (at most {self.max_coeffs})"
        if cfg.active_sh_degree(case.gaussians.sh.shape[1]) > self.max_sh_degree:
            return f"SH degree {cfg.sh_degree} (at most {self.max_sh_degree})"
        if self.camera_model == "simple_pinhole" and c.fx != c.fy:
            return f"fx {c.fx} != fy {c.fy}"
        if not self.principal_point and (c.cx != c.width / 2 or c.cy != c.height / 2):
            return f"principal point ({c.cx}, {c.cy}) off the image centre"
        if not self.background and any(cfg.background):
            return f"background {cfg.background}"
        return None


# ---------------------------------------------------------------------------------------------
# cameras
# ---------------------------------------------------------------------------------------------


@st.composite
def cameras(draw, caps: Capabilities = Capabilities(), *, off_centre: bool = False,
            anisotropic: bool = False, axis_aligned: bool = False, min_size=(16, 12)) -> refgs.Camera:
    """A camera 3-6 units from the origin looking at it (OpenCV frame, CNV-01..CNV-03).

    Hypothesis draws the image size and a seed; fx in [30, 120] and the pose come from the seed.
    off_centre: principal point anywhere in the middle 40 % of the image (cx != W/2), if ``caps``
    allows; anisotropic: fy = fx * [0.7, 1.4], if ``caps`` is a pinhole model; axis_aligned:
    identity rotation, centre at (0, 0, -d) (camera z = world z + d exactly, for exact depth ties).
    """
    W = draw(st.integers(min_size[0], MAX_WIDTH), label="width")
    H = draw(st.integers(min_size[1], MAX_HEIGHT), label="height")
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="camera_seed"))
    fx = rng.uniform(30.0, 120.0)
    fy = fx * rng.uniform(0.7, 1.4) if anisotropic else fx
    if caps.camera_model == "simple_pinhole":
        fy = fx
    cx, cy = W / 2, H / 2
    if off_centre:
        cx, cy = W * rng.uniform(0.3, 0.7), H * rng.uniform(0.3, 0.7)
        if not caps.principal_point:
            cx, cy = W / 2, H / 2
    dist = rng.uniform(3.0, 6.0)
    if axis_aligned:
        w2c = np.eye(4)
        w2c[2, 3] = float(np.float32(dist))
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        return refgs.Camera(w2c, K, W, H)
    azim = rng.uniform(0.0, 2 * np.pi)
    elev = rng.uniform(-1.2, 1.2)
    eye = dist * np.array([np.cos(elev) * np.sin(azim), np.sin(elev), -np.cos(elev) * np.cos(azim)])
    return refgs.Camera.look_at(eye, rng.uniform(-0.3, 0.3, 3), fx=fx, fy=fy, width=W, height=H,
                                cx=cx, cy=cy)


def unproject(camera: refgs.Camera, u, v, z) -> np.ndarray:
    """World points whose camera-space depth is ``z`` and image coordinates (u, v) (CNV-08)."""
    u, v, z = (np.asarray(a, np.float64) for a in (u, v, z))
    t = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
    R, tw = camera.rotation, camera.translation
    return (t - tw) @ R                      # R^T (t - tw), row vectors


# ---------------------------------------------------------------------------------------------
# scales and quaternions
# ---------------------------------------------------------------------------------------------


class ScaleFamily:
    """A named distribution of log-scale triples: ``family(rng, n) -> (n, 3)`` (CNV-06).

    Scenes draw one seed per Gaussian with hypothesis (so shrinking removes Gaussians) and sample
    its parameters from these families with numpy (cheap, and never an exact boundary value).
    """

    def __init__(self, name: str, sample):
        self.name, self._sample = name, sample

    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return np.asarray(self._sample(rng, n), np.float64).reshape(n, 3)

    def __repr__(self) -> str:
        return f"ScaleFamily({self.name})"


def log_scales(lo: float = -4.0, hi: float = -0.5) -> ScaleFamily:
    """Three independent log-scales uniform in [lo, hi]."""
    return ScaleFamily(f"log_scales({lo}, {hi})", lambda rng, n: rng.uniform(lo, hi, (n, 3)))


def tiny_scales() -> ScaleFamily:
    """Scales 1e-7 .. 3e-3: far below a pixel, so the 0.3 dilation dominates (PRJ-04, HARD-06)."""
    return log_scales(-16.0, -6.0)


def huge_scales() -> ScaleFamily:
    """Scales e^1 .. e^4 (3 to 55 world units): splats covering the whole image (HARD-11)."""
    return log_scales(1.0, 4.0)


def needle_scales(max_ratio: float = 1e3, max_long: float = 0.0) -> ScaleFamily:
    """One axis 10..max_ratio times the other two, the long axis at most e^max_long world units
    (needles; HARD-02, HARD-13 go further)."""
    def sample(rng, n):
        base = rng.uniform(-6.0, -2.0, n)
        out = np.repeat(base[:, None], 3, axis=1)
        axis = rng.integers(0, 3, n)
        out[np.arange(n), axis] = np.minimum(base + rng.uniform(np.log(10.0), np.log(max_ratio), n),
                                             max_long)
        return out
    return ScaleFamily(f"needle_scales({max_ratio}, {max_long})", sample)


def either(*families: ScaleFamily) -> ScaleFamily:
    """Each Gaussian from one of ``families``, chosen uniformly."""
    def sample(rng, n):
        pick = rng.integers(0, len(families), n)
        out = np.empty((n, 3))
        for i, fam in enumerate(families):
            if np.any(pick == i):
                out[pick == i] = fam(rng, int(np.sum(pick == i)))
        return out
    return ScaleFamily("either(" + ", ".join(f.name for f in families) + ")", sample)


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniformly random rotations (normalised Gaussian 4-vectors; any scale is legal, CNV-05)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_sh(rng: np.random.Generator, n: int, k: int = SH_COEFFS, dc_sigma: float = 1.0,
              rest_sigma: float = 0.3) -> np.ndarray:
    """SH coefficients (N, K, 3): DC ~ N(0, dc_sigma) (so some colours clamp at 0, CNV-10), the
    higher bands ~ N(0, rest_sigma)."""
    sh = rng.normal(0.0, rest_sigma, (n, k, 3))
    sh[:, 0, :] = rng.normal(0.0, dc_sigma, (n, 3))
    return sh


# ---------------------------------------------------------------------------------------------
# Gaussians relative to a camera
# ---------------------------------------------------------------------------------------------


def _interval(spec, rng, n):
    """n values from a (lo, hi) interval, or from a sampler ``spec(rng, n)``."""
    return spec(rng, n) if callable(spec) else rng.uniform(spec[0], spec[1], n)


@st.composite
def in_front_of(draw, camera: refgs.Camera, *, n=(1, MAX_GAUSSIANS), u=(-0.1, 1.1), v=(-0.1, 1.1),
                z=(1.0, 8.0), scales=None, logits=(-2.0, 5.0), dc_sigma=1.0, rest_sigma=0.3,
                z_values=None) -> refgs.Gaussians:
    """Gaussians whose means project to image fractions ``u`` x ``v`` at depths ``z``.

    Hypothesis draws one seed per Gaussian (shrinking removes Gaussians); each Gaussian's
    position, depth, log-scales (``scales``: a :class:`ScaleFamily`, default :func:`log_scales`),
    opacity logit, rotation and SH come from its seed.  ``u``, ``v``, ``z``, ``logits`` are
    (lo, hi) intervals or samplers ``f(rng, n)``; ``z_values``: depths from this finite set
    instead (exact depth ties).
    """
    scales = log_scales() if scales is None else scales
    seeds = draw(st.lists(st.integers(0, 2**32 - 1), min_size=n[0], max_size=n[1]), label="gaussians")
    m = len(seeds)
    if m == 0:
        return refgs.Gaussians.empty(SH_COEFFS)
    rows = []
    for sd in seeds:
        rng = np.random.default_rng(sd)
        zz = rng.choice(np.asarray(z_values, np.float64), 1) if z_values is not None else _interval(z, rng, 1)
        rows.append((_interval(u, rng, 1)[0], _interval(v, rng, 1)[0], float(zz[0]), scales(rng, 1)[0],
                     _interval(logits, rng, 1)[0], random_quats(rng, 1)[0],
                     random_sh(rng, 1, SH_COEFFS, dc_sigma, rest_sigma)[0]))
    uf, vf, zz = (np.array([r[i] for r in rows]) for i in range(3))
    means = unproject(camera, uf * camera.width, vf * camera.height, zz)
    return refgs.Gaussians(means, np.stack([r[3] for r in rows]), np.stack([r[5] for r in rows]),
                           np.array([r[4] for r in rows]), np.stack([r[6] for r in rows]))


def straddling_near_plane(camera: refgs.Camera, profile: str, n=(1, 24)):
    """Depths from 0.3x to 3x the profile's near plane: some culled, some kept (PRJ-02, PRF-01)."""
    near = PROFILES[profile].near
    return in_front_of(camera, n=n, u=(0.2, 0.8), v=(0.2, 0.8), z=(0.3 * near, 3.0 * near),
                       scales=log_scales(np.log(near) - 4.0, np.log(near) - 1.5))


def off_screen(camera: refgs.Camera, n=(1, 16)):
    """Means beyond the frustum clamp (0.35 to 3.5 image widths outside, left or right) with
    scales large enough that their tails still reach the image (PRJ-03, HARD-01)."""
    def u_out(rng, k):
        left = rng.random(k) < 0.5
        return np.where(left, rng.uniform(-2.5, -0.35, k), rng.uniform(1.35, 3.5, k))
    return in_front_of(camera, n=n, u=u_out, v=(-1.0, 2.0), z=(2.0, 6.0), scales=log_scales(-1.0, 0.7))


@st.composite
def opaque_stack(draw, camera: refgs.Camera, n=(2, 20)) -> refgs.Gaussians:
    """2-20 nearly opaque Gaussians (logits 3..20) stacked along one ray, jittered by a couple of
    pixels, at increasing depths: T falls below 1e-4 inside the stack (RAS-05, HARD-07)."""
    rng0 = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="stack_seed"))
    u0 = rng0.uniform(0.3, 0.7) * camera.width
    v0 = rng0.uniform(0.3, 0.7) * camera.height
    seeds = draw(st.lists(st.integers(0, 2**32 - 1), min_size=n[0], max_size=n[1]), label="layers")
    rngs = [np.random.default_rng(sd) for sd in seeds]
    du, dv, dz, ls, lg = (np.array([f(r) for r in rngs]) for f in (
        lambda r: r.uniform(-2, 2), lambda r: r.uniform(-2, 2), lambda r: r.uniform(0.05, 0.5),
        lambda r: r.uniform(-2.5, -1.2) + r.uniform(-0.3, 0.3, 3), lambda r: r.uniform(3, 20)))
    z = 2.0 + np.cumsum(dz)
    means = unproject(camera, u0 + du, v0 + dv, z)
    quats = np.stack([random_quats(r, 1)[0] for r in rngs])
    sh = np.stack([random_sh(r, 1)[0] for r in rngs])
    return refgs.Gaussians(means, ls, quats, lg, sh)


def depth_ties(camera: refgs.Camera, n=(2, 24)):
    """Gaussians on three depth layers with exactly equal depths in both dtypes (RAS-02): use with
    an ``axis_aligned`` camera, whose camera z is world z + d computed exactly."""
    return in_front_of(camera, n=n, u=(0.1, 0.9), v=(0.1, 0.9), z_values=(2.0, 3.0, 5.0),
                       scales=log_scales(-2.5, -1.0), logits=(0.0, 4.0)).map(_round_depths(camera))


def _round_depths(camera):
    def fix(g: refgs.Gaussians) -> refgs.Gaussians:
        m = np.asarray(g.means, np.float32).astype(np.float64)
        # world z chosen so that z + d is exactly 2, 3 or 5 in float32 and float64
        d = camera.translation[2]
        t = m[:, 2] + d
        m[:, 2] = np.round(t) - d
        return g.replace(means=m)
    return fix


@st.composite
def near_degenerate_quaternions(draw, gaussians: refgs.Gaussians, exponents=(-30.0, 3.0)):
    """The same Gaussians with quaternion norms 10**[-30, 3]: tiny but non-zero, to be
    normalised exactly (CNV-05, HARD-06).  A zero quaternion is an error, see the error checks."""
    if len(gaussians) == 0:
        return gaussians
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="quat_norm_seed"))
    e = rng.uniform(exponents[0], exponents[1], len(gaussians))
    return gaussians.replace(quats=gaussians.quats * (10.0 ** e)[:, None])


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------


@st.composite
def cases(draw, caps: Capabilities, *, camera: dict | None = None, gaussians=None,
          sh_degree: str = "any", background: bool = False, opacity_scale: bool = False,
          antialiased: bool = False, label: str = "scene") -> Case:
    """A complete Case inside ``caps`` (its profile, SH degree, camera model, principal point
    and background).

    camera: options of :func:`cameras`; gaussians: a function camera -> strategy of Gaussians
    (default :func:`in_front_of`); sh_degree: "any" (0..max), "zero", "max" or "partial" (an
    explicit degree below what K carries, SH-01); background: draw a random background colour
    (RAS-06) if ``caps`` allows; opacity_scale: draw RenderConfig.opacity_scale (API-02);
    antialiased: gsplat's compensation (PRJ-08).
    """
    profile, max_sh_degree = caps.profile, caps.max_sh_degree
    cam = draw(cameras(caps, **(camera or {})), label="camera")
    g = draw(gaussians(cam) if gaussians is not None else in_front_of(cam), label="gaussians")
    g = caps.fit_sh(g)
    if sh_degree == "zero":
        deg = 0
    elif sh_degree == "max":
        deg = max_sh_degree
    elif sh_degree == "partial":
        deg = draw(st.integers(0, max(0, max_sh_degree - 1)), label="sh_degree")
    else:
        deg = draw(st.integers(0, max_sh_degree), label="sh_degree")
    bg = (0.0, 0.0, 0.0)
    if background and caps.background:
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="background_seed"))
        bg = tuple(float(x) for x in rng.uniform(0.0, 1.0, 3))
    scale = None
    if opacity_scale and len(g):
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="opacity_scale_seed"))
        scale = rng.uniform(0.0, 1.5, len(g))
    cfg = refgs.RenderConfig(profile=profile, sh_degree=deg, background=bg,
                             antialiased=antialiased, opacity_scale=scale)
    seed = draw(st.integers(0, 2**31 - 1), label="cotangent_seed")
    return Case(g, cam, cfg, seed=seed, label=label)
