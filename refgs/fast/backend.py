"""refgs.fast as a backend object at a fixed profile and dtype (the backend protocol, ORC-01/ORC-02).

The registry (refgs.backends) builds :class:`FastBackend` for the names ``fast``, ``fast64``,
``fast32`` and ``fast32g`` (training, ``refgs bench``, the conformance suite); the module-level
objects below are the same backends by ``module:object``::

    python -m oracle check --backend refgs.fast:fast_float32      (= --backend fast32)

The oracle hands float64 Gaussians whose values are exactly representable in the backend's
dtype; :class:`FastBackend` casts them (and opacity_scale) to its dtype and renders with
:func:`refgs.fast.render`.  ``fast_float32_geom64`` is the mixed precision
``render(..., geometry="float64")`` (float32 compositing of a float64 per-Gaussian stage): the
oracle holds it to the float32 tolerances and near-tie bands, which cover it with room to spare.
"""
from __future__ import annotations

import numpy as np

from .. import __version__
from ..types import RenderConfig
from .render import GEOMETRY_PRECISIONS, render, render_backward

PROFILES = ("inria", "gsplat")
DTYPES = ("float32", "float64")


class FastBackend:
    """refgs.fast for one (profile, dtype)."""

    max_sh_degree = 3
    has_backward = True
    supports_opacity_scale = True

    def __init__(self, profile: str = "inria", dtype: str = "float64", geometry: str = "input"):
        if profile not in PROFILES:
            raise ValueError(f"profile: expected one of {PROFILES}, got {profile!r}")
        if dtype not in DTYPES:
            raise ValueError(f"dtype: expected one of {DTYPES}, got {dtype!r}")
        if geometry not in GEOMETRY_PRECISIONS:
            raise ValueError(f"geometry: expected one of {GEOMETRY_PRECISIONS}, got {geometry!r}")
        self.profile, self.dtype, self.geometry = profile, dtype, geometry
        self.name = f"refgs.fast-{profile}-{dtype}" + ("-geom64" if geometry == "float64" else "")
        import numba
        self.version = f"refgs {__version__}, numba {numba.__version__}"
        self.supports_antialiased = profile == "gsplat"

    def __repr__(self) -> str:
        extra = f", geometry={self.geometry!r}" if self.geometry != "input" else ""
        return f"FastBackend({self.profile!r}, {self.dtype!r}{extra})"

    def render(self, gaussians, camera, config: RenderConfig | None = None):
        config = RenderConfig(profile=self.profile) if config is None else config
        if config.profile != self.profile:
            raise ValueError(f"RenderConfig.profile: this backend renders {self.profile!r}, "
                             f"got {config.profile!r}")
        dt = np.dtype(self.dtype)
        if config.opacity_scale is not None:
            s = np.asarray(config.opacity_scale)
            if s.dtype.kind == "f":
                s = s.astype(dt)
            config = RenderConfig(profile=config.profile, sh_degree=config.sh_degree,
                                  background=config.background, antialiased=config.antialiased,
                                  opacity_scale=s)
        if hasattr(gaussians, "astype") and getattr(gaussians, "dtype", None) != dt:
            gaussians = gaussians.astype(dt)
        return render(gaussians, camera, config, geometry=self.geometry)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return render_backward(out, v_image, v_alpha, v_depth)


fast_float64 = FastBackend("inria", "float64")
fast_float32 = FastBackend("inria", "float32")
fast_gsplat_float64 = FastBackend("gsplat", "float64")
fast_gsplat_float32 = FastBackend("gsplat", "float32")
#: float32 compositing of a float64 per-Gaussian stage (docs/fast.md, "Mixed precision")
fast_float32_geom64 = FastBackend("inria", "float32", geometry="float64")
