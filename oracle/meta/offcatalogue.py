"""Renderers with catalogue deviations *and* defects the catalogue does not name (DEV-03).

The diagnosis must name the catalogue deviations and localise each off-catalogue defect to its
stage (oracle/residual.py).  ``OffCatalogue`` composes refgs' stage functions as refgs.render does
(COV-01, PRJ-*, SH-*, RAS-*), with the deviations' profile options on and a defect planted
between two stages; it returns image and alpha only, as an outside renderer would, and never
modifies refgs.

    DEFECTS                       name -> (stage, what)
    OffCatalogue(deviations, defects)

    cov_rotation_sign    COV  the rotation's (1, 2) entry with the wrong sign (2 (yz + wx) typed
                              for 2 (yz - wx): R is no longer a rotation)
    ellipse_mirrored     PRJ  the conic's off-diagonal with the wrong sign (the projected ellipse
                              mirrored: a sign slip in J or in the 2x2 inverse)
    sort_by_distance     RAS  fragments sorted by distance from the camera, not by t_z
    sh_x_sign            SH   the sign of the degree-1 basis function in x flipped (CNV-09's
                              -C1 x read as +C1 x; not the reversed view direction, which flips
                              all three)
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit

import refgs
from refgs.deviations import apply_deviations, check_deviations
from refgs.render import resolve_profile

#: name -> (the stage it sits in, what it does)
DEFECTS = {
    "cov_rotation_sign": ("COV", "the rotation matrix's (1, 2) entry with the wrong sign"),
    "ellipse_mirrored": ("PRJ", "the projected conic's off-diagonal with the wrong sign"),
    "sh_x_sign": ("SH", "the degree-1 basis function in x with the wrong sign"),
    "sort_by_distance": ("RAS", "fragments sorted by distance from the camera instead of t_z"),
}


class OffCatalogue:
    """refgs (inria, float64) with catalogue ``deviations`` on and off-catalogue ``defects``
    (names of :data:`DEFECTS`); render returns {"image", "alpha"}."""

    profile, dtype = "inria", "float64"
    max_sh_degree = refgs.constants.SH_MAX_DEGREE
    has_backward = False
    supports_opacity_scale = True
    supports_antialiased = False

    def __init__(self, deviations=(), defects=()):
        self.deviations = check_deviations(deviations, "OffCatalogue.deviations")
        unknown = sorted(set(defects) - set(DEFECTS))
        if unknown:
            raise ValueError(f"OffCatalogue.defects: expected names from {sorted(DEFECTS)}, got {unknown}")
        self.defects = frozenset(defects)
        self.name = (f"refgs-inria + {', '.join(sorted(self.deviations)) or 'no deviation'} "
                     f"+ off-catalogue {', '.join(sorted(self.defects)) or 'none'}")
        self.version = refgs.__version__

    def render(self, gaussians, camera, config):
        g, d = gaussians, self.defects
        refgs.validate_inputs(g, camera, config)
        profile = apply_deviations(resolve_profile(config), self.deviations)
        W, H = int(camera.width), int(camera.height)
        cov = refgs.covariance_3d(g.quats, g.log_scales, profile)
        cov3d = cov["cov3d"]
        if "cov_rotation_sign" in d:
            R = cov["R"].copy()
            R[:, 1, 2] *= -1.0
            M = R * cov["scales"][:, None, :]
            cov3d = M @ np.swapaxes(M, -1, -2)
        o = expit(g.opacity_logits)
        scale = np.ones_like(o) if config.opacity_scale is None else np.asarray(config.opacity_scale, np.float64)
        proj = refgs.project_gaussians(g.means, cov3d, o * scale, camera, profile, config.antialiased)
        conics = proj["conics"].copy()
        if "ellipse_mirrored" in d:
            conics[:, 1] *= -1.0
        deg = config.active_sh_degree(g.sh.shape[1])
        sh = g.sh.copy()
        if "sh_x_sign" in d and sh.shape[1] > 3:
            sh[:, 3] *= -1.0                           # the coefficient of -C1 x (CNV-09)
        colors = refgs.eval_sh_colors(g.means, sh, camera.center, deg, profile)["colors"]
        key = proj["depths"]
        if "sort_by_distance" in d:
            key = np.linalg.norm(g.means - camera.center, axis=-1)
        g2d = {"means2d": proj["means2d"], "conics": conics, "opacities": o * scale * proj["comp"],
               "colors": colors, "depths": proj["depths"]}
        lists = refgs.build_tile_lists(proj["tile_rect"], key, proj["visible"], W, H)
        comp = refgs.composite(g2d, lists, W, H, profile, np.asarray(config.background, np.float64))
        return {"image": comp["image"], "alpha": comp["alpha"]}


__all__ = ["DEFECTS", "OffCatalogue"]
