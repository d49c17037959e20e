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
    supports_background     bool  (optional, default True; a non-black background, RAS-06)
    supports_principal_point bool (optional, default True; cx, cy anywhere, not only W/2, H/2,
                            CNV-03)
    camera_model   "pinhole" | "simple_pinhole"    (optional, default "pinhole": fx and fy;
                            "simple_pinhole": one focal length, fx == fy, CNV-03)
    unavailable_reason      str or None (optional): when set, render/render_backward cannot run
                            here (e.g. no CUDA device); render-level checks report "n/a" with it,
                            stage checks still run
    known_differences       a sequence of mappings with ``check``, optional ``clause``,
                            ``reason`` and optional ``link`` (optional): failures the author
                            knows of, reported as "known" (oracle/known.py, ORC-02)

Checks outside the declared capabilities are "n/a" with the reason, and every scene the oracle
draws stays inside them (SH degree and coefficients, camera model, principal point, background,
opacity_scale, antialiasing).

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

import inspect
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import refgs

PROFILES = ("inria", "gsplat")
DTYPES = ("float32", "float64")
#: camera models a backend may declare (CNV-03): fx, fy, cx, cy / one focal length fx == fy
CAMERA_MODELS = ("pinhole", "simple_pinhole")
#: names of the optional stage functions, in pipeline order (ORC-01)
STAGES = ("covariance", "projection", "sh", "composite")
#: fields of a backend's render output the oracle compares when present (API-04)
PIXEL_OUTPUTS = ("image", "alpha", "depth", "n_contrib")
GAUSSIAN_OUTPUTS = ("radii", "means2d", "depths", "conics", "colors", "opacities", "visible")
GRAD_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


class BackendError(ValueError):
    """The backend could not be loaded or declares impossible capabilities; the message says which."""


# ---------------------------------------------------------------------------------------------
# Cases: the oracle's unit of input
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """One input for a check (a *test case*): the scene -- float64 Gaussians and a camera --, the
    render config, and a seed for the cotangents of gradient checks.

    ``label`` names the strategy or hard-case builder that produced it (shown in reports).
    Not to be confused with ``refgs.data.colmap.Scene``, a COLMAP reconstruction.
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

    def with_gaussians(self, g: refgs.Gaussians) -> "Case":
        cfg = self.config
        if cfg.opacity_scale is not None and len(g) != self.n:
            raise ValueError("Case.with_gaussians: use subset() when opacity_scale is set")
        return Case(g, self.camera, cfg, self.seed, self.label)

    def subset(self, index) -> "Case":
        """The scene restricted to Gaussians ``index`` (opacity_scale follows)."""
        cfg = self.config
        if cfg.opacity_scale is not None:
            cfg = _replace_config(cfg, opacity_scale=np.asarray(cfg.opacity_scale)[index])
        return Case(self.gaussians.subset(index), self.camera, cfg, self.seed, self.label)

    def with_camera(self, camera: refgs.Camera) -> "Case":
        return Case(self.gaussians, camera, self.config, self.seed, self.label)

    def with_config(self, **changes) -> "Case":
        return Case(self.gaussians, self.camera, _replace_config(self.config, **changes),
                    self.seed, self.label)

    def rounded(self, dtype: str) -> "Case":
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
        return Case(g, cam, cfg, self.seed, self.label)


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
    supports_background: bool = True
    supports_principal_point: bool = True
    camera_model: str = "pinhole"
    known_differences: tuple = ()
    #: the isolated worker serving ``obj`` (oracle/isolation.py), None when ``obj`` is the backend
    #: itself, loaded in this process
    session: Any = None

    def capabilities(self) -> dict:
        """JSON-ready description (the report's ``backend`` block)."""
        return {"profile": self.profile, "dtype": self.dtype, "max_sh_degree": self.max_sh_degree,
                "has_backward": self.has_backward,
                "backward_cotangents": sorted(["v_image", *self.backward_kwargs]),
                "supports_antialiased": self.supports_antialiased,
                "supports_opacity_scale": self.supports_opacity_scale,
                "supports_background": self.supports_background,
                "supports_principal_point": self.supports_principal_point,
                "camera_model": self.camera_model,
                "stages": sorted(self.stages), "unavailable_reason": self.unavailable_reason}

    def description(self) -> dict:
        """Everything but the object, as plain data (what an isolated worker sends back)."""
        return {"spec": self.spec, "name": self.name, "version": self.version,
                **self.capabilities(), "known_differences": [dict(k) for k in self.known_differences]}

    @classmethod
    def from_description(cls, d: dict, obj: Any, session: Any = None) -> "BackendInfo":
        """The inverse of :meth:`description`; ``obj`` stands in for the backend (a proxy whose
        ``stage_<name>`` methods exist for every stage named in ``d``)."""
        return cls(obj=obj, spec=d["spec"], name=d["name"], version=d["version"],
                   profile=d["profile"], dtype=d["dtype"], max_sh_degree=int(d["max_sh_degree"]),
                   has_backward=bool(d["has_backward"]),
                   backward_kwargs=frozenset(d["backward_cotangents"]) - {"v_image"},
                   supports_antialiased=bool(d["supports_antialiased"]),
                   supports_opacity_scale=bool(d["supports_opacity_scale"]),
                   stages={s: getattr(obj, f"stage_{s}") for s in d["stages"]},
                   unavailable_reason=d.get("unavailable_reason"),
                   supports_background=bool(d["supports_background"]),
                   supports_principal_point=bool(d["supports_principal_point"]),
                   camera_model=str(d["camera_model"]),
                   known_differences=tuple(d.get("known_differences", ())), session=session)


def import_object(spec: str) -> Any:
    """Import ``module[:attr.path]`` (the current directory first on sys.path), as the backend
    registry does (refgs.backends.import_object); BackendError naming the missing piece."""
    from refgs.backends import import_object as registry_import

    try:
        return registry_import(spec, "--backend")
    except ValueError as exc:
        raise BackendError(str(exc)) from None


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
    model = getattr(obj, "camera_model", "pinhole")
    if model not in CAMERA_MODELS:
        raise BackendError(f"backend {where}: attribute 'camera_model' must be one of {CAMERA_MODELS}, "
                           f"got {model!r}")
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
                       unavailable_reason=getattr(obj, "unavailable_reason", None) or None,
                       supports_background=bool(getattr(obj, "supports_background", True)),
                       supports_principal_point=bool(getattr(obj, "supports_principal_point", True)),
                       camera_model=model, known_differences=_known_differences(obj, where))


def load_backend(spec: str) -> BackendInfo:
    """The backend ``spec`` -- a name of the backend registry (refgs.backends: ``ref64``,
    ``fast32``, ``torch64``, ``gsplat``, ...) or ``module:object`` -- resolved by the registry,
    then ``describe_backend``; BackendError naming the problem."""
    from refgs.backends import get_backend

    try:
        backend = get_backend(spec, flag="--backend", runnable=False)
    except ValueError as exc:
        raise BackendError(str(exc)) from None
    return describe_backend(backend.renderer, spec)


#: keys of one ``known_differences`` entry (ORC-02); ``check`` and ``reason`` are required
KNOWN_KEYS = ("check", "clause", "reason", "link")


def _known_differences(obj: Any, where: str) -> tuple:
    """The backend's ``known_differences`` as a tuple of plain dicts of strings (the keys of
    :data:`KNOWN_KEYS`); BackendError naming the entry when one is malformed.  Whether each names
    a real check and clause is checked by oracle/known.py."""
    raw = getattr(obj, "known_differences", None) or ()
    if isinstance(raw, (str, bytes)) or not hasattr(raw, "__iter__"):
        raise BackendError(f"backend {where}: attribute 'known_differences' must be a list of "
                           f"mappings, got {type(raw).__name__}")
    out = []
    for i, entry in enumerate(raw):
        if not hasattr(entry, "get") or not entry.get("check") or not entry.get("reason"):
            raise BackendError(f"backend {where}: known_differences[{i}] must be a mapping with "
                               f"'check' and 'reason' (and optionally 'clause', 'link'), got {entry!r}")
        extra = set(entry) - set(KNOWN_KEYS)
        if extra:
            raise BackendError(f"backend {where}: known_differences[{i}] has unknown keys "
                               f"{sorted(extra)}; expected {KNOWN_KEYS}")
        out.append({k: str(entry[k]) for k in KNOWN_KEYS if entry.get(k) is not None})
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Reading a backend's outputs
# ---------------------------------------------------------------------------------------------


class Malformed:
    """Stands in for an output the backend returned that is not a numeric array (an isolated
    worker could not send it); ``message`` says what it was.  The evaluators report it as a
    malformed output (status "error")."""

    def __init__(self, message: str):
        self.message = message

    def __repr__(self) -> str:
        return f"Malformed({self.message!r})"


def get_field(obj: Any, name: str):
    """``obj.name`` or ``obj[name]`` as a numpy array, or None when absent (torch tensors are
    detached and moved to the CPU); a :class:`Malformed` stand-in is returned as it is."""
    if obj is None:
        return None
    if isinstance(obj, dict):
        val = obj.get(name)
    else:
        val = getattr(obj, name, None)
    if val is None or isinstance(val, Malformed):
        return val
    if hasattr(val, "detach"):                 # a torch tensor, without importing torch
        val = val.detach().cpu().numpy()
    return np.asarray(val)


# Helpers for backends with their own parameterisation live in refgs (re-exported here).
from refgs.activations import raw_gradients, to_activated  # noqa: E402,F401
