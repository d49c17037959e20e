"""refgs itself as oracle backends: float64 (the reference, as a backend) and float32.

    refgs_float64, refgs_float32                  inria profile
    refgs_gsplat_float64, refgs_gsplat_float32    gsplat profile (antialiasing supported)

The float32 backends convert the Gaussians to float32 and run refgs, which then computes every
intermediate in float32 (CNV-11): a model of a float32 GPU backend with its rounding.  All four
expose refgs' stage functions, so the oracle's per-stage checks run too.
"""
from __future__ import annotations

import numpy as np

import refgs
from refgs.render import resolve_profile


class RefgsBackend:
    """refgs.render / render_backward at a fixed dtype and profile (ORC-01)."""

    max_sh_degree = refgs.constants.SH_MAX_DEGREE
    has_backward = True
    supports_opacity_scale = True

    def __init__(self, profile: str = "inria", dtype: str = "float64"):
        if profile not in refgs.PROFILES:
            raise ValueError(f"profile: expected one of {sorted(refgs.PROFILES)}, got {profile!r}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype: expected 'float32' or 'float64', got {dtype!r}")
        self.profile, self.dtype = profile, dtype
        self.supports_antialiased = profile == "gsplat"
        self.name = f"refgs-{profile}-{dtype}"
        self.version = refgs.__version__

    def _cast(self, a):
        return np.asarray(a, dtype=self.dtype)

    def render(self, gaussians, camera, config=None):
        config = refgs.RenderConfig(profile=self.profile) if config is None else config
        return refgs.render(gaussians.astype(self.dtype), camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return refgs.render_backward(out, v_image, v_alpha, v_depth)

    # ---- stage functions (ORC-01) -----------------------------------------------------------
    def stage_covariance(self, quats, log_scales):
        return refgs.covariance_3d(self._cast(quats), self._cast(log_scales))["cov3d"]

    def stage_projection(self, means, cov3d, opacities, camera, config):
        return refgs.project_gaussians(self._cast(means), self._cast(cov3d), self._cast(opacities),
                                       camera, resolve_profile(config), config.antialiased)

    def stage_sh(self, means, sh, campos, degree):
        return refgs.eval_sh_colors(self._cast(means), self._cast(sh), self._cast(campos), degree)["colors"]

    def stage_composite(self, means2d, conics, opacities, colors, depths, radii, camera, config):
        profile = resolve_profile(config)
        W, H = int(camera.width), int(camera.height)
        g2d = {"means2d": self._cast(means2d), "conics": self._cast(conics),
               "opacities": self._cast(opacities), "colors": self._cast(colors),
               "depths": self._cast(depths)}
        radii = np.asarray(radii)
        rect, ok = refgs.tile_rectangles(g2d["means2d"], radii[:, 0], radii[:, 1], W, H, profile)
        visible = ok & np.any(radii > 0, axis=-1)
        lists = refgs.build_tile_lists(rect, g2d["depths"], visible, W, H)
        return refgs.composite(g2d, lists, W, H, profile, self._cast(config.background))


refgs_float64 = RefgsBackend("inria", "float64")
refgs_float32 = RefgsBackend("inria", "float32")
refgs_gsplat_float64 = RefgsBackend("gsplat", "float64")
refgs_gsplat_float32 = RefgsBackend("gsplat", "float32")

__all__ = ["RefgsBackend", "refgs_float64", "refgs_float32", "refgs_gsplat_float64",
           "refgs_gsplat_float32"]
