"""What a backend is, how the oracle loads it, and helpers to write one (ORC-01, ORC-02).

A *backend* is any importable object -- a module, a class instance -- with

    render(gaussians, camera, config) -> out
        gaussians: refgs.Gaussians (float64 arrays holding values exactly representable in the
        backend's dtype), camera: refgs.Camera, config: refgs.RenderConfig whose ``profile`` is the
        backend's.  ``out`` has at least ``.image`` (H,W,3) and ``.alpha`` (H,W) (attributes or
        mapping keys; numpy-convertible).  Optional fields, compared when present: ``depth``,
        ``n_contrib``, ``radii``, ``means2d``, ``depths``, ``conics``, ``colors``, ``opacities``,
        ``visible`` (meanings and shapes as refgs.RenderOutput, API-04).
        Invalid input (a zero quaternion, a NaN, a wrong shape) raises ValueError (API-03).

and capability attributes

    profile        "inria" | "gsplat"               (required)
    dtype          "float32" | "float64"            (required; the working dtype, CNV-11)
    name, version  strings for the report           (optional)
    max_sh_degree  0..3                             (optional, default 3)
    has_backward   bool                             (optional, default: render_backward exists)
    supports_antialiased    bool  (optional, default False; gsplat profile only, PRJ-08)
    supports_opacity_scale  bool  (optional, default True; RenderConfig.opacity_scale, API-02)
    unavailable_reason      str or None (optional): when set, render/render_backward cannot run
                            here (e.g. no CUDA device); render-level checks report "n/a" with it,
                            stage checks still run

and optionally

    render_backward(out, v_image[, v_alpha=None, v_depth=None]) -> gradients
        with ``means`` (N,3), ``log_scales`` (N,3), ``quats`` (N,4), ``opacity_logits`` (N,),
        ``sh`` (N,K,3) = dL/d(raw parameter) and optionally ``means2d`` (N,2) in pixels (API-05).
        v_alpha / v_depth are used only if the signature names them.
    stage_covariance(quats (N,4), log_scales (N,3)) -> cov3d (N,3,3)                   (COV-01)
    stage_projection(means, cov3d, opacities, camera, config) -> mapping/object with
        means2d (N,2), conics (N,3), depths (N,), radii (N,2) [, cov2d, visible]       (PRJ-*)
    stage_sh(means (N,3), sh (N,K,3), campos (3,), degree) -> colors (N,3)            (SH-*)
    stage_composite(means2d, conics, opacities, colors, depths, radii, camera, config)
        -> mapping/object with image (H,W,3), alpha (H,W) [, depth, n_contrib]        (RAS-*)

A backend that works in activated parameters (scales, opacities, unit quaternions) converts with
:func:`to_activated` and maps its gradients back with :func:`raw_gradients`.
oracle/adapters/template.py is a complete worked template.
"""
from __future__ import annotations

import importlib
import inspect
import os
import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import refgs

PROFILES = ("inria", "gsplat")
DTYPES = ("float32", "float64")
#: names of the optional stage functions, in pipeline order (ORC-01)
STAGES = ("covariance", "projection", "sh", "composite")
#: fields of a backend's render output the oracle compares when present (API-04)
PIXEL_OUTPUTS = ("image", "alpha", "depth", "n_contrib")
GAUSSIAN_OUTPUTS = ("radii", "means2d", "depths", "conics", "colors", "opacities", "visible")
GRAD_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


class BackendError(ValueError):
    """The backend could not be loaded or declares impossible capabilities; the message says which."""


# ---------------------------------------------------------------------------------------------
# Scenes: the oracle's unit of input
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scene:
    """One input for a check: float64 Gaussians, a camera, a config, and a seed for cotangents.

    ``label`` names the strategy or hard-case builder that produced it (shown in reports).
    """

    gaussians: refgs.Gaussians
    camera: refgs.Camera
    config: refgs.RenderConfig
    seed: int = 0
    label: str = ""

    @property
    def n(self) -> int:
        return len(self.gaussians)

    def summary(self) -> dict:
        """The scene in a few numbers (what a report shows)."""
        g, c, cfg = self.gaussians, self.camera, self.config
        return {"label": self.label, "n_gaussians": self.n, "width": int(c.width),
                "height": int(c.height), "K": [[float(v) for v in row] for row in np.asarray(c.K)],
                "profile": str(cfg.profile), "sh_degree": cfg.sh_degree,
                "sh_coeffs": int(g.sh.shape[1]), "background": [float(v) for v in cfg.background],
                "antialiased": bool(cfg.antialiased),
                "opacity_scale": cfg.opacity_scale is not None, "seed": int(self.seed)}

    def with_gaussians(self, g: refgs.Gaussians) -> "Scene":
        cfg = self.config
        if cfg.opacity_scale is not None and len(g) != self.n:
            raise ValueError("Scene.with_gaussians: use subset() when opacity_scale is set")
        return Scene(g, self.camera, cfg, self.seed, self.label)

    def subset(self, index) -> "Scene":
        """The scene restricted to Gaussians ``index`` (opacity_scale follows)."""
        cfg = self.config
        if cfg.opacity_scale is not None:
            cfg = _replace_config(cfg, opacity_scale=np.asarray(cfg.opacity_scale)[index])
        return Scene(self.gaussians.subset(index), self.camera, cfg, self.seed, self.label)

    def with_camera(self, camera: refgs.Camera) -> "Scene":
        return Scene(self.gaussians, camera, self.config, self.seed, self.label)

    def with_config(self, **changes) -> "Scene":
        return Scene(self.gaussians, self.camera, _replace_config(self.config, **changes),
                     self.seed, self.label)

    def rounded(self, dtype: str) -> "Scene":
        """Every float input rounded to ``dtype`` and held in float64 (ORC-05): the backend and the
        float64 reference then see exactly the same numbers."""
        if dtype == "float64":
            return self
        dt = np.dtype(dtype)

        def r(a):
            return np.asarray(a, dtype=np.float64).astype(dt).astype(np.float64)

        g = refgs.Gaussians(*(r(getattr(self.gaussians, f)) for f in refgs.Gaussians.FIELDS))
        c = self.camera
        cam = refgs.Camera(r(c.world_to_camera), r(c.K), int(c.width), int(c.height))
        cfg = self.config
        bg = tuple(float(v) for v in r(cfg.background))
        scale = None if cfg.opacity_scale is None else r(cfg.opacity_scale)
        cfg = _replace_config(cfg, background=bg, opacity_scale=scale)
        return Scene(g, cam, cfg, self.seed, self.label)


def _replace_config(cfg: refgs.RenderConfig, **changes) -> refgs.RenderConfig:
    kw = {"profile": cfg.profile, "sh_degree": cfg.sh_degree, "background": cfg.background,
          "antialiased": cfg.antialiased, "opacity_scale": cfg.opacity_scale}
    kw.update(changes)
    return refgs.RenderConfig(**kw)


# ---------------------------------------------------------------------------------------------
# Loading a backend and reading its capabilities
# ---------------------------------------------------------------------------------------------


@dataclass
class BackendInfo:
    """A loaded backend and its resolved capabilities (ORC-02)."""

    obj: Any
    spec: str
    name: str
    version: str
    profile: str
    dtype: str
    max_sh_degree: int
    has_backward: bool
    backward_kwargs: frozenset
    supports_antialiased: bool
    supports_opacity_scale: bool
    stages: dict = field(default_factory=dict)
    unavailable_reason: str | None = None

    def capabilities(self) -> dict:
        """JSON-ready description (the report's ``backend`` block)."""
        return {"profile": self.profile, "dtype": self.dtype, "max_sh_degree": self.max_sh_degree,
                "has_backward": self.has_backward,
                "backward_cotangents": sorted(["v_image", *self.backward_kwargs]),
                "supports_antialiased": self.supports_antialiased,
                "supports_opacity_scale": self.supports_opacity_scale,
                "stages": sorted(self.stages), "unavailable_reason": self.unavailable_reason}


def import_object(spec: str) -> Any:
    """Import ``module[:attr.path]``; the current directory is put on sys.path first."""
    if not isinstance(spec, str) or not spec.strip():
        raise BackendError("--backend: expected 'module:object' (e.g. "
                           "oracle.adapters.refgs_backend:refgs_float32), got an empty value")
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    mod_name, _, attr = spec.strip().partition(":")
    try:
        obj = importlib.import_module(mod_name)
    except ImportError as exc:
        raise BackendError(f"--backend {spec}: cannot import module {mod_name!r} ({exc})") from None
    for part in filter(None, attr.split(".")):
        if not hasattr(obj, part):
            raise BackendError(f"--backend {spec}: module {mod_name!r} has no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


def describe_backend(obj: Any, spec: str = "") -> BackendInfo:
    """Read the capability attributes of ``obj`` (module docstring); BackendError if invalid."""
    where = spec or type(obj).__name__
    if not callable(getattr(obj, "render", None)):
        raise BackendError(f"backend {where}: has no callable render(gaussians, camera, config)")
    profile = getattr(obj, "profile", None)
    if profile not in PROFILES:
        raise BackendError(f"backend {where}: attribute 'profile' must be one of {PROFILES}, got {profile!r}")
    dtype = str(getattr(obj, "dtype", None))
    if dtype not in DTYPES:
        raise BackendError(f"backend {where}: attribute 'dtype' must be one of {DTYPES}, got {dtype!r}")
    deg = getattr(obj, "max_sh_degree", refgs.constants.SH_MAX_DEGREE)
    if not isinstance(deg, (int, np.integer)) or not 0 <= deg <= refgs.constants.SH_MAX_DEGREE:
        raise BackendError(f"backend {where}: attribute 'max_sh_degree' must be an int in 0..3, got {deg!r}")
    bwd = getattr(obj, "render_backward", None)
    has_bwd = bool(getattr(obj, "has_backward", callable(bwd))) and callable(bwd)
    kwargs = frozenset()
    if has_bwd:
        try:
            params = inspect.signature(bwd).parameters
            kwargs = frozenset(k for k in ("v_alpha", "v_depth") if k in params or any(
                p.kind is p.VAR_KEYWORD for p in params.values()))
        except (TypeError, ValueError):
            kwargs = frozenset()
    stages = {s: getattr(obj, f"stage_{s}") for s in STAGES if callable(getattr(obj, f"stage_{s}", None))}
    name = getattr(obj, "name", None) or getattr(obj, "__name__", None) or type(obj).__name__
    version = getattr(obj, "version", None) or getattr(obj, "__version__", None) or "unknown"
    return BackendInfo(obj=obj, spec=spec, name=str(name), version=str(version), profile=profile,
                       dtype=dtype, max_sh_degree=int(deg), has_backward=has_bwd,
                       backward_kwargs=kwargs,
                       supports_antialiased=bool(getattr(obj, "supports_antialiased", False))
                       and profile == "gsplat",
                       supports_opacity_scale=bool(getattr(obj, "supports_opacity_scale", True)),
                       stages=stages,
                       unavailable_reason=getattr(obj, "unavailable_reason", None) or None)


def load_backend(spec: str) -> BackendInfo:
    """``import_object`` + ``describe_backend``."""
    return describe_backend(import_object(spec), spec)


# ---------------------------------------------------------------------------------------------
# Reading a backend's outputs
# ---------------------------------------------------------------------------------------------


def get_field(obj: Any, name: str):
    """``obj.name`` or ``obj[name]`` as a numpy array, or None when absent (torch tensors are
    detached and moved to the CPU)."""
    if obj is None:
        return None
    if isinstance(obj, dict):
        val = obj.get(name)
    else:
        val = getattr(obj, name, None)
    if val is None:
        return None
    if hasattr(val, "detach"):                 # a torch tensor, without importing torch
        val = val.detach().cpu().numpy()
    return np.asarray(val)


# Helpers for backends with their own parameterisation live in refgs (re-exported here).
from refgs.activations import raw_gradients, to_activated  # noqa: E402,F401
