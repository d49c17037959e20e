"""The one backend registry: a name or ``module:object`` -> a renderer with its capabilities.

A *backend* is an object with the signatures of :func:`refgs.render` and
:func:`refgs.render_backward`::

    render(gaussians, camera, config) -> RenderOutput-like (image, alpha, radii, means2d, ...)
    render_backward(out, v_image, v_alpha=None, v_depth=None) -> refgs.Gradients

and the capability attributes of the conformance protocol (``profile``, ``dtype``,
``has_backward``, ...; docs/oracle.md, ORC-01/ORC-02).  Three callers resolve backends here and
nowhere else, with one spelling:

    refgs train --backend NAME          the trainer (refgs.runs), at the run's profile and dtype
    refgs bench --backends NAME ...     speed against error (refgs.analysis.bench)
    python -m oracle check --backend NAME   conformance (oracle/protocol.py ``load_backend``)

NAME is a key of :data:`BACKENDS` or ``module:object`` (any importable object with the methods
above; the current folder is searched first): an outside renderer plugs in everywhere as
``mypackage.mymodule:my_backend``.  An entry's capabilities are data (:class:`Entry`): the dtype
and profile it renders (None: the caller's), its optional training helpers (``ssim_and_grad``,
``l1_ssim_loss``, ``adam_update``, TRN-08), its near-tie bands (bench) and the optional extra it needs.  Entries
whose code needs numba or torch are named by ``module:object`` strings and imported only when
chosen, so ``import refgs`` stays numpy-only; the torch and gsplat entries live in the
conformance suite's adapters and refgs imports them only on use.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from dataclasses import dataclass

import numpy as np

from .constants import SH_MAX_DEGREE
from .errors import ConfigError

#: What a name that renders any profile / dtype gets when the caller names none (the
#: reference's defaults: RenderConfig.profile and float64, CNV-11).
DEFAULT_PROFILE = "inria"
DEFAULT_DTYPE = "float64"
DTYPES = ("float32", "float64")
#: Optional helpers a backend may offer the trainer (TRN-08): the loss's SSIM with its gradient
#: (the signature of refgs.metrics.ssim.ssim_and_grad), the whole loss w_l1 L1 + w_ssim (1 - SSIM)
#: with its gradient (the signature of refgs.fast.ssim.l1_ssim_loss) and Adam's update of one
#: parameter (the signature of refgs.fast.adam.adam_update; False when it does not apply).
HELPERS = ("ssim_and_grad", "l1_ssim_loss", "adam_update")


class BackendUnavailable(ConfigError):
    """A known backend that cannot be used here or for this purpose (a missing optional
    dependency, no device, another profile or dtype, no backward); ``reason`` says why."""

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Entry:
    """One registry name and its capabilities.

    target    ``module:object``: a factory called as ``factory(profile=, dtype=, **options)``,
              or (``factory=False``) a ready object
    label     what reports call it; ``{dtype}`` is filled in
    dtype, profile   what it renders; None: any (the caller's, else DEFAULT_*)
    helpers   (helper name, ``module:function``) pairs, see HELPERS
    bands     near-tie bands of a float32 backend (refgs.fast.ties; the bench)
    extra     the optional dependency it needs (``pip install 'refgs[extra]'``)
    """

    name: str
    target: str
    label: str
    dtype: str | None = None
    profile: str | None = None
    factory: bool = True
    options: tuple = ()
    helpers: tuple = ()
    bands: str = "float32"
    extra: str | None = None


_FAST_HELPERS = (("ssim_and_grad", "refgs.fast.ssim:ssim_and_grad"),
                 ("l1_ssim_loss", "refgs.fast.ssim:l1_ssim_loss"),
                 ("adam_update", "refgs.fast.adam:adam_update"))
_REF = "refgs.backends:ReferenceBackend"
_FAST = "refgs.fast.backend:FastBackend"
_TORCH = "oracle.adapters.torch_backend:TorchBackend"

#: name -> Entry.  "reference" / "fast": the trainer's names (any dtype and profile);
#: ref64 ... gsplat: the bench's names (one dtype each); gswarp32, taichi32, taichi64: outside
#: renderers (docs/conformance.md).
BACKENDS: dict[str, Entry] = {e.name: e for e in (
    Entry("reference", _REF, "refgs reference {dtype}"),
    Entry("fast", _FAST, "refgs.fast {dtype}", helpers=_FAST_HELPERS, extra="numba"),
    Entry("ref64", _REF, "refgs reference {dtype}", dtype="float64"),
    Entry("ref32", _REF, "refgs reference {dtype}", dtype="float32"),
    Entry("fast64", _FAST, "refgs.fast {dtype}", dtype="float64", helpers=_FAST_HELPERS,
          extra="numba"),
    Entry("fast32", _FAST, "refgs.fast {dtype}", dtype="float32", helpers=_FAST_HELPERS,
          extra="numba"),
    Entry("fast32g", _FAST, "refgs.fast float32 compositing, float64 geometry", dtype="float32",
          options=(("geometry", "float64"),), helpers=_FAST_HELPERS,
          bands="float32-compositing", extra="numba"),
    Entry("torch64", _TORCH, "torch autograd transcription {dtype}", dtype="float64",
          extra="torch"),
    Entry("torch32", _TORCH, "torch autograd transcription {dtype}", dtype="float32",
          extra="torch"),
    Entry("gsplat", "oracle.adapters.gsplat_backend:gsplat_backend",
          "gsplat 1.5.3 rasterization float32", dtype="float32", profile="gsplat",
          factory=False, extra="gsplat"),
    # renderers written outside this project, behind the conformance suite's adapters
    # (docs/conformance.md); each needs its optional extra
    Entry("gswarp32", "oracle.adapters.gswarp_backend:gswarp_float32", "gswarp 1.1.0 {dtype}",
          dtype="float32", profile="inria", factory=False, extra="gswarp"),
    Entry("taichi32", "oracle.adapters.taichi_splatting_backend:taichi_float32",
          "taichi-splatting 0.13.0 {dtype}", dtype="float32", profile="inria", factory=False,
          extra="taichi"),
    Entry("taichi64", "oracle.adapters.taichi_splatting_backend:taichi_float64",
          "taichi-splatting 0.13.0 {dtype}", dtype="float64", profile="inria", factory=False,
          extra="taichi"),
)}


#: The trainer's backends, fastest first: ``refgs train`` and ``refgs demo`` without ``--backend``
#: use the first that loads here (refgs.fast, certified by the oracle: docs/conformance.md; about
#: 17 times the reference's speed on fern, TRN-12).  Every run records the name it used.
TRAIN_PREFERENCE = ("fast", "reference")


def default_backend() -> str:
    """The first name of TRAIN_PREFERENCE whose code imports on this machine ("fast" when numba
    imports, else "reference")."""
    for name in TRAIN_PREFERENCE:
        try:
            importlib.import_module(BACKENDS[name].target.partition(":")[0])
        except ImportError:
            continue
        return name
    return TRAIN_PREFERENCE[-1]


def register_backend(entry: Entry) -> None:
    """Make ``entry`` available under ``entry.name`` (a later registration replaces one)."""
    BACKENDS[str(entry.name)] = entry


def available_backends() -> list[str]:
    """The registry's names, in registration order."""
    return list(BACKENDS)


def _check_spec(spec, flag: str) -> None:
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"{flag}: expected a backend name ({', '.join(BACKENDS)}) or "
                          f"'module:object', got {spec!r}")


def import_object(spec: str, flag: str = "--backend"):
    """Import ``module[:attr.path]`` with the current folder first on sys.path; ConfigError
    naming ``flag`` and the missing module or attribute."""
    _check_spec(spec, flag)
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    mod_name, _, attr = spec.strip().partition(":")
    try:
        obj = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ConfigError(f"{flag} {spec}: cannot import module {mod_name!r} ({exc})") from None
    for part in filter(None, attr.split(".")):
        if not hasattr(obj, part):
            raise ConfigError(f"{flag} {spec}: module {mod_name!r} has no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


class Backend:
    """A renderer as the registry resolved it.

    ``render`` / ``render_backward`` are the renderer's own; ``renderer`` is the object itself
    (what the conformance suite describes); ``name``, ``label``, ``profile``, ``dtype``,
    ``has_backward``, ``bands`` and ``unavailable_reason`` are its capabilities.  The helpers of
    HELPERS exist as attributes only when the entry (or the renderer) provides them: the trainer
    uses a helper when present (TRN-08).
    """

    def __init__(self, spec: str, renderer, label: str, bands: str, helpers: dict):
        self.spec, self.renderer, self.label, self.bands = spec, renderer, label, bands
        self.render = renderer.render
        bwd = getattr(renderer, "render_backward", None)
        self.has_backward = callable(bwd) and bool(getattr(renderer, "has_backward", True))
        self.render_backward = bwd
        self.profile = getattr(renderer, "profile", None)
        self.dtype = None if getattr(renderer, "dtype", None) is None else str(renderer.dtype)
        self.name = str(getattr(renderer, "name", None) or spec)
        self.unavailable_reason = getattr(renderer, "unavailable_reason", None) or None
        for key in HELPERS:
            fn = helpers.get(key, getattr(renderer, key, None))
            if fn is not None:
                setattr(self, key, fn)

    def __repr__(self) -> str:
        return f"Backend({self.spec!r}, {self.label!r})"


def _unavailable(flag: str, spec: str, reason: str) -> BackendUnavailable:
    return BackendUnavailable(f"{flag} {spec}: {' '.join(str(reason).split())}", reason)


def _choose(flag: str, spec: str, what: str, fixed, wanted, default):
    if fixed is not None and wanted is not None and fixed != wanted:
        raise _unavailable(flag, spec, f"renders {what} {fixed} only, not {wanted}")
    return fixed or wanted or default


def _from_entry(entry: Entry, profile, dtype, flag: str) -> Backend:
    spec = entry.name
    profile = _choose(flag, spec, "profile", entry.profile, profile, DEFAULT_PROFILE)
    dtype = _choose(flag, spec, "dtype", entry.dtype, dtype, DEFAULT_DTYPE)
    mod_name, _, attr = entry.target.partition(":")
    try:
        module = importlib.import_module(mod_name)
        helpers = {k: import_object(v, flag) for k, v in entry.helpers}
    except ImportError as exc:
        raise _unavailable(flag, spec, str(exc)) from None
    factory = getattr(module, attr)
    obj = factory(profile=profile, dtype=dtype, **dict(entry.options)) if entry.factory else factory
    return Backend(spec, obj, entry.label.format(dtype=dtype, profile=profile), entry.bands, helpers)


def _from_object(spec: str, profile, dtype, flag: str) -> Backend:
    obj = import_object(spec, flag)
    if not callable(getattr(obj, "render", None)):
        raise ConfigError(f"{flag} {spec}: has no callable render(gaussians, camera, config)")
    _choose(flag, spec, "profile", getattr(obj, "profile", None), profile, None)
    _choose(flag, spec, "dtype", getattr(obj, "dtype", None), dtype, None)
    return Backend(spec, obj, spec, "float32", {})


def _is_module(name: str) -> bool:
    """Whether ``name`` is an importable top-level module (a backend given as a module, e.g. a
    file mybackend.py in the current folder)."""
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def get_backend(spec: str, profile: str | None = None, dtype: str | None = None, *,
                flag: str = "--backend", runnable: bool = True) -> Backend:
    """The backend named ``spec`` (a key of BACKENDS or ``module:object``), rendering ``profile``
    and ``dtype`` (None: the entry's or the object's own, else DEFAULT_PROFILE / DEFAULT_DTYPE).

    ConfigError (one line naming ``flag``) for an unknown name; BackendUnavailable for a known
    one that cannot serve: a missing optional dependency, another fixed profile or dtype, and
    with ``runnable`` (the trainer, the bench) an ``unavailable_reason`` or no backward.  The
    conformance suite passes ``runnable=False``: it reports those itself."""
    _check_spec(spec, flag)
    spec = spec.strip()
    if dtype is not None:
        dtype = np.dtype(dtype).name
    if spec in BACKENDS:
        be = _from_entry(BACKENDS[spec], profile, dtype, flag)
    elif ":" in spec or "." in spec or _is_module(spec):
        be = _from_object(spec, profile, dtype, flag)
    else:
        raise ConfigError(f"{flag}: unknown backend {spec!r}; available: "
                          f"{', '.join(BACKENDS)}, or module:object")
    if runnable and be.unavailable_reason:
        raise _unavailable(flag, spec, be.unavailable_reason)
    if runnable and not be.has_backward:
        raise _unavailable(flag, spec, "has no render_backward")
    return be


# --- the numpy specification as a backend -----------------------------------------------------
class ReferenceBackend:
    """:func:`refgs.render` / :func:`refgs.render_backward` at a profile and dtype.

    Gaussians in another dtype are converted first, so that every intermediate is computed in
    ``dtype`` (CNV-11: float32 models a float32 GPU backend with its rounding).  ``profile`` /
    ``dtype`` None: render whatever is given.  The stage functions let the conformance suite
    check each stage on its own (ORC-01)."""

    max_sh_degree = SH_MAX_DEGREE
    has_backward = True
    supports_opacity_scale = True

    def __init__(self, profile: str | None = DEFAULT_PROFILE, dtype: str | None = DEFAULT_DTYPE):
        from . import PROFILES, __version__
        if profile is not None and profile not in PROFILES:
            raise ValueError(f"profile: expected one of {sorted(PROFILES)}, got {profile!r}")
        if dtype is not None and dtype not in DTYPES:
            raise ValueError(f"dtype: expected one of {DTYPES}, got {dtype!r}")
        self.profile, self.dtype = profile, dtype
        self.supports_antialiased = profile in ("gsplat", None)
        self.name = f"refgs-{profile or 'any'}-{dtype or 'any'}"
        self.version = __version__

    def __repr__(self) -> str:
        return f"ReferenceBackend({self.profile!r}, {self.dtype!r})"

    def _cast(self, a):
        return np.asarray(a) if self.dtype is None else np.asarray(a, dtype=self.dtype)

    def render(self, gaussians, camera, config=None):
        from .render import render
        from .types import RenderConfig
        config = RenderConfig(profile=self.profile or DEFAULT_PROFILE) if config is None else config
        if self.profile is not None and config.profile != self.profile:
            raise ValueError(f"RenderConfig.profile: this backend renders {self.profile!r}, "
                             f"got {config.profile!r}")
        if self.dtype is not None and getattr(gaussians, "dtype", None) != np.dtype(self.dtype):
            gaussians = gaussians.astype(self.dtype)
        return render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        from .render import render_backward
        return render_backward(out, v_image, v_alpha, v_depth)

    # ---- stage functions (ORC-01) -----------------------------------------------------------
    def stage_covariance(self, quats, log_scales):
        from .covariance import covariance_3d
        return covariance_3d(self._cast(quats), self._cast(log_scales))["cov3d"]

    def stage_projection(self, means, cov3d, opacities, camera, config):
        from .projection import project_gaussians
        from .render import resolve_profile
        return project_gaussians(self._cast(means), self._cast(cov3d), self._cast(opacities),
                                 camera, resolve_profile(config), config.antialiased)

    def stage_sh(self, means, sh, campos, degree):
        from .sh import eval_sh_colors
        return eval_sh_colors(self._cast(means), self._cast(sh), self._cast(campos),
                              degree)["colors"]

    def stage_composite(self, means2d, conics, opacities, colors, depths, radii, camera, config):
        from .projection import tile_rectangles
        from .rasterize import build_tile_lists, composite
        from .render import resolve_profile
        profile = resolve_profile(config)
        W, H = int(camera.width), int(camera.height)
        g2d = {"means2d": self._cast(means2d), "conics": self._cast(conics),
               "opacities": self._cast(opacities), "colors": self._cast(colors),
               "depths": self._cast(depths)}
        radii = np.asarray(radii)
        rect, ok = tile_rectangles(g2d["means2d"], radii[:, 0], radii[:, 1], W, H, profile)
        visible = ok & np.any(radii > 0, axis=-1)
        lists = build_tile_lists(rect, g2d["depths"], visible, W, H)
        return composite(g2d, lists, W, H, profile, self._cast(config.background))


__all__ = ["BACKENDS", "Entry", "Backend", "BackendUnavailable", "ReferenceBackend",
           "get_backend", "register_backend", "available_backends", "import_object",
           "default_backend", "DEFAULT_PROFILE", "DEFAULT_DTYPE", "HELPERS", "TRAIN_PREFERENCE"]
