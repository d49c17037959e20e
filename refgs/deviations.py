"""The catalogue of named deviations: variants of one stage that real renderers (or well-known
mistakes) have (docs/spec/deviations.md, clauses DEV-01, DEV-02).

A deviation changes one stage's option -- a field of :class:`refgs.constants.Profile` -- away
from the reference; ``RenderConfig(deviations={...})`` switches deviations on, and with none on
the reference path is unchanged, bit for bit.  The two profiles are named combinations:
``apply_deviations(INRIA, PROFILE_CHOICES["gsplat"])`` is the gsplat profile.

    DEVIATIONS                  name -> Deviation, in pipeline order
    PROFILE_CHOICES             profile name -> the deviations from inria that make it
    check_deviations(names)     frozenset of valid, compatible names, or ValueError
    apply_deviations(p, names)  the Profile ``p`` with the deviations' options set
    incompatible(names)         why a set cannot be switched on together, or None

Each deviation carries a *witness*: a minimal scene (one to five Gaussians, at most 32 x 16
pixels) on which it changes ``render`` (or, for backward-only ones, ``render_backward``).
Citations: diff-gaussian-rasterization@59f5f77 ("the original") and gsplat 1.5.3 as in
docs/spec/profiles.md; issue numbers as in docs/spec/hard_cases.md.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .constants import SH_C0, Profile
from .types import Camera, Gaussians, RenderConfig


@dataclass(frozen=True)
class Witness:
    """A minimal scene that shows a deviation; the camera sits at the origin looking down +z.

    at          per Gaussian (u, v, z): image position of the mean in pixels (CNV-08) and depth
    log_scales  per Gaussian one value (isotropic) or three; quats (w, x, y, z); logits; rgb
    sh1         degree-1 coefficients (3 x 3) shared by every Gaussian, or None (degree 0)
    size        (W, H); focal f = fx = fy; centre (cx, cy) or None for the image centre
    background  RenderConfig.background; backward: the deviation shows in render_backward only
    """

    at: tuple
    log_scales: tuple = (-1.0,)
    quats: tuple = ((1.0, 0.0, 0.0, 0.0),)
    logits: tuple = (2.0,)
    rgb: tuple = ((0.9, 0.5, 0.2),)
    sh1: tuple | None = None
    size: tuple = (16, 16)
    focal: float = 16.0
    centre: tuple | None = None
    background: tuple = (0.0, 0.0, 0.0)
    backward: bool = False

    def build(self, profile: str = "inria") -> tuple[Gaussians, Camera, RenderConfig]:
        """(Gaussians, Camera, RenderConfig) of the witness, float64."""
        n = len(self.at)

        def rows(values, width):
            arr = np.asarray(values, np.float64).reshape(len(values), -1)
            arr = np.repeat(arr, n, axis=0) if len(arr) == 1 else arr
            return np.repeat(arr, width, axis=1) if arr.shape[1] == 1 and width > 1 else arr

        W, H = self.size
        cx, cy = (W / 2, H / 2) if self.centre is None else self.centre
        f = float(self.focal)
        uvz = np.asarray(self.at, np.float64)
        z = uvz[:, 2]
        means = np.stack([(uvz[:, 0] - cx) * z / f, (uvz[:, 1] - cy) * z / f, z], -1)
        k = 1 if self.sh1 is None else 4
        sh = np.zeros((n, k, 3))
        sh[:, 0, :] = (rows(self.rgb, 3) - 0.5) / SH_C0
        if self.sh1 is not None:
            sh[:, 1:, :] = np.asarray(self.sh1, np.float64)
        g = Gaussians(means, rows(self.log_scales, 3), rows(self.quats, 4),
                      rows(self.logits, 1)[:, 0], sh)
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        return g, Camera(np.eye(4), K, int(W), int(H)), RenderConfig(
            profile=profile, background=tuple(float(b) for b in self.background))


@dataclass(frozen=True)
class Deviation:
    """One named deviation: the stage and clause it departs from, the Profile options it sets,
    who does it (with the citation), and its witness (None: the oracle cannot observe it)."""

    name: str
    label: str
    stage: str
    clause: str
    changes: tuple
    who: str
    witness: Witness | None
    backward_only: bool = False
    excludes: tuple = ()
    note: str = ""

    @property
    def observable(self) -> bool:
        return self.witness is not None

    def options(self) -> dict:
        return dict(self.changes)


def _logit(o: float) -> float:
    return float(np.log(o / (1.0 - o)))


# ---- witnesses ------------------------------------------------------------------------------
#: an elongated, rotated Gaussian (rotation and quaternion conventions, the conic's off-diagonal)
_ROTATED = Witness(at=((8.3, 7.6, 4.0),), log_scales=((-0.5, -2.5, -2.0),),
                   quats=((0.8, 0.2, 0.3, 0.45),))
#: a large Gaussian far right of the frustum limit (x/z = 1.2 > 1.3 tan(fov/2) = 0.65), its tail
#: on the image
_OFF_SCREEN = Witness(at=((27.2, 8.3, 4.0),), log_scales=(0.3,), logits=(3.0,))
#: a Gaussian much smaller than a pixel, its mean off the pixel centre
_TINY = Witness(at=((8.2, 7.7, 4.0),), log_scales=(-7.0,))
#: opaque Gaussians on a pixel centre and on a pixel corner (the centre under pixel_centre_0):
#: o G = 0.99966 > every cap
_OPAQUE = Witness(at=((8.5, 8.5, 4.0), (4.0, 4.0, 4.0)), log_scales=(-2.0,), logits=(8.0,))
#: five opaque Gaussians stacked on one pixel centre: T = 0.1, 0.005, 1.5e-4, then 3e-6 < 1e-4
_STACK = Witness(at=tuple((8.5, 8.5, z) for z in (2.0, 3.0, 4.0, 5.0, 6.0)), log_scales=(-2.5,),
                 logits=tuple(_logit(o) for o in (0.9, 0.95, 0.97, 0.98, 0.9)),
                 rgb=((0.9, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.1, 0.9), (0.9, 0.9, 0.1), (0.1, 0.9, 0.9)))


def _isotropic_log_scale(var2d: float, z: float = 4.0, f: float = 16.0) -> float:
    """log s of an isotropic Gaussian at depth z whose undilated 2D variance is var2d px^2."""
    return float(np.log(np.sqrt(var2d) * z / f))


def _dev(name, label, stage, clause, changes, who, witness, **kw) -> Deviation:
    return Deviation(name, label, stage, clause, tuple(sorted(changes.items())), who, witness, **kw)


_CATALOGUE = [
    # ---- covariance (COV) ---------------------------------------------------------------------
    _dev("quat_xyzw", "quaternions read (x, y, z, w)", "COV", "CNV-04", {"quat_order": "xyzw"},
         "scalar-last conventions (scipy.spatial.transform.Rotation.from_quat reads x, y, z, w); "
         "the original (rot = (r, x, y, z)) and gsplat (wxyz) are scalar-first", _ROTATED),
    _dev("quat_unnormalised", "quaternions not normalised", "COV", "CNV-05",
         {"quat_normalization": "none"},
         "the original's CUDA computeCov3D has the normalisation commented out "
         "(forward.cu L127 `glm::vec4 q = rot;// / glm::length(rot);`) and relies on the Python "
         "F.normalize: a backend feeding raw parameters to that kernel skips it",
         dataclasses.replace(_ROTATED, quats=((1.6, 0.4, 0.6, 0.9),))),
    _dev("quat_normalize_eps", "quaternions normalised as q / max(|q|, 1e-12)", "COV", "CNV-05",
         {"quat_normalization": "eps"},
         "gsplat's pure-torch _quat_to_rotmat (F.normalize, eps 1e-12; cuda/_math.py)",
         dataclasses.replace(_ROTATED, quats=((0.8e-14, 0.2e-14, 0.3e-14, 0.45e-14),))),
    _dev("rotation_transposed", "rotation composed transposed (R^T S S^T R)", "COV", "COV-01",
         {"rotation_transposed": True},
         "glm is column-major: the original stores R transposed and builds M = S R, "
         "Sigma = M^T M (forward.cu computeCov3D); the row-major formula written into a "
         "glm::mat3 without that compensation gives R^T", _ROTATED),
    # ---- projection (PRJ) ---------------------------------------------------------------------
    _dev("near_cull_off", "no near-plane cull (only t_z <= 0 culled)", "PRJ", "PRJ-02",
         {"near": 0.0, "near_inclusive": True, "far": float("inf")},
         "the original's in_frustum test (auxiliary.h L154, t_z <= 0.2) left out; only points "
         "behind the camera are dropped",
         Witness(at=((8.3, 7.8, 0.005),), log_scales=(-7.0,))),
    _dev("near_gsplat", "gsplat's depth range (cull t_z < 0.01 or > 1e10)", "PRJ", "PRF-01",
         {"near": 0.01, "near_inclusive": False, "far": 1e10},
         "gsplat 1.5.3 rendering.py:43-44, ProjectionEWA3DGSFused.cu:72",
         Witness(at=((8.3, 7.8, 0.1),), log_scales=(-4.0,))),
    _dev("no_frustum_clamp", "no frustum clamp in the Jacobian", "PRJ", "PRJ-03",
         {"frustum_clamp": False},
         "the EWA Jacobian as the 3DGS paper writes it; the clamp to 1.3 tan(fov/2) exists only in "
         "the code (forward.cu computeCov2D L81-86)", _OFF_SCREEN,
         excludes=("frustum_principal_point", "clamp_depth_grad_original", "clamp_forward_only")),
    _dev("frustum_principal_point", "frustum clamp limits from the principal point", "PRJ", "PRF-02",
         {"frustum_symmetric": False},
         "gsplat 1.5.3 include/Utils.cuh:514-519 (lim_x_pos = (W - cx)/fx + 0.3 tan_fovx)",
         Witness(at=((-4.8, 8.3, 4.0),), log_scales=(-0.4,), logits=(3.0,), centre=(4.0, 8.0))),
    _dev("clamp_depth_grad_original", "the original's depth gradient under the clamp (#75)",
         "PRJ", "PRJ-07", {"exact_clamp_depth_grad": False},
         "diff-gaussian-rasterization #75: backward.cu computeCov2DCUDA keeps 2 fx tx / tz^3 with "
         "the clamped tx (HARD-01)", dataclasses.replace(_OFF_SCREEN, backward=True),
         backward_only=True),
    _dev("clamp_forward_only", "frustum clamp ignored by the backward", "PRJ", "PRJ-07",
         {"clamp_in_backward": False},
         "old gsplat: \"FoV clip applied in the forward pass but not the backward\" "
         "(gsplat PR #172, HARD-05)", dataclasses.replace(_OFF_SCREEN, backward=True),
         backward_only=True),
    _dev("no_dilation", "no low-pass dilation", "PRJ", "PRJ-04", {"eps2d": 0.0},
         "the 3DGS paper's Sigma2D without the code's +0.3 (forward.cu L110-111); the oracle's "
         "planted bug (a) (ORC-10)", _TINY),
    _dev("dilation_0.1", "low-pass dilation 0.1 instead of 0.3", "PRJ", "PRJ-04", {"eps2d": 0.1},
         "Mip-Splatting's 2D filter size on gsplat (yzslab/gaussian-splatting-lightning "
         "internal/renderers/gsplat_mip_splatting_renderer_v2.py `filter_2d_kernel_size: float = "
         "0.1`), here without its opacity compensation", _TINY),
    _dev("det_cull_nonpositive", "determinant cull det <= 0", "PRJ", "PRF-03",
         {"det_cull_nonpositive": True},
         "gsplat 1.5.3 ProjectionEWA3DGSFused.cu:155 (`det <= 0.f`)", None,
         note="after the dilation det >= 0.09 in exact arithmetic; the rules differ only on "
              "rounding artefacts, which no witness scene can pin down"),
    _dev("radius_3sigma", "radius 3 sqrt(lambda_max) without the 0.1 floor", "PRJ", "PRJ-05",
         {"radius_rule": "eig", "radius_sigma": 3.0, "eig_floor": 0.0},
         "the textbook 3-sigma bound of the largest eigenvalue (the original adds the floor, "
         "forward.cu L229-232; gsplat v1.0.0's torch reference floors at 0.01)",
         Witness(at=((11.0, 8.3, 4.0),), log_scales=(_isotropic_log_scale(3.55),), size=(32, 16),
                 centre=(11.0, 8.3))),
    _dev("radius_axis_3.33", "radius 3.33 sigma per axis", "PRJ", "PRF-04",
         {"radius_rule": "axis", "radius_sigma": 3.33, "eig_floor": 0.0, "opacity_cull": False},
         "gsplat without opacities passed to the projection (Common.h GAUSSIAN_EXTEND 3.33f)",
         Witness(at=((7.0, 8.3, 4.0), (24.0, 8.3, 4.0)), log_scales=(_isotropic_log_scale(9.7),),
                 logits=(2.0, -3.0), size=(32, 16))),
    _dev("radius_opacity_aware", "opacity-aware per-axis radius, opacity cull", "PRJ", "PRF-04",
         {"radius_rule": "axis", "radius_sigma": 3.33, "eig_floor": 0.0, "opacity_cull": True},
         "gsplat 1.5.3 ProjectionEWA3DGSFused.cu:164-186 (extend = min(3.33, sqrt(2 ln(255 o))), "
         "cull o < 1/255)",
         Witness(at=((7.0, 8.3, 4.0), (24.0, 8.3, 4.0)), log_scales=(_isotropic_log_scale(9.7),),
                 logits=(-3.0, -6.0), size=(32, 16))),
    _dev("gsplat_tiles", "gsplat's tile rectangle and off-image cull", "PRJ", "PRF-08",
         {"tile_rule": "gsplat", "offscreen_cull": True},
         "gsplat 1.5.3 IntersectTile.cu:62-77 (floor/ceil of (m -+ r)/16), "
         "ProjectionEWA3DGSFused.cu:193-194",
         Witness(at=((10.45, 8.3, 4.0),), log_scales=(_isotropic_log_scale(3.7),), logits=(3.0,),
                 size=(32, 16))),
    # ---- colour (SH) --------------------------------------------------------------------------
    _dev("sh_dir_reversed", "SH view direction reversed (camera minus mean)", "SH", "SH-03",
         {"sh_dir_reversed": True},
         "a sign mistake against the original's dir = mean - campos (forward.cu "
         "computeColorFromSH): every odd band flips",
         Witness(at=((6.3, 9.6, 4.0),), sh1=((0.3, 0.1, -0.2), (0.2, -0.3, 0.1), (-0.1, 0.2, 0.3)))),
    _dev("colour_clamp_01", "colours clamped to [0, 1]", "SH", "CNV-10", {"colour_max": 1.0},
         "8-bit colour paths of viewers; the original clamps at 0 only "
         "(clamp_min(sh2rgb + 0.5, 0), gaussian_renderer/__init__.py)",
         Witness(at=((8.3, 7.6, 4.0),), rgb=((1.6, 0.5, 1.3),))),
    # ---- rasterization (RAS) ------------------------------------------------------------------
    _dev("pixel_centre_0", "pixels sampled at (j, i) instead of (j + 0.5, i + 0.5)", "RAS", "CNV-08",
         {"pixel_offset": 0.0},
         "the original's pixel loop (integer pixf, forward.cu L282) with a means2d of fx x/z + cx, "
         "without ndc2Pix's -0.5; the oracle's planted bug (f)",
         Witness(at=((8.2, 7.7, 4.0),), log_scales=(-2.0,))),
    _dev("alpha_cap_0.999", "alpha cap 0.999", "RAS", "PRF-05", {"alpha_max": 0.999},
         "gsplat 1.5.3 RasterizeToPixels3DGSFwd.cu:148", _OPAQUE),
    _dev("alpha_cap_off", "no alpha cap", "RAS", "RAS-04", {"alpha_max": 1.0},
         "alpha = o G without the min: the cap is what bounds 1/(1 - alpha) in the backward "
         "(gsplat #556, HARD-07)", _OPAQUE, excludes=("no_cap_gradient",)),
    _dev("alpha_skip_off", "no 1/255 alpha skip", "RAS", "RAS-04", {"alpha_skip": False},
         "dense compositing of every fragment (the original skips alpha < 1/255, forward.cu L342; "
         "the skip is what makes gsplat #1011's support collapse, HARD-09)",
         Witness(at=((8.3, 7.6, 4.0),), log_scales=(0.0,), logits=(_logit(0.003),))),
    _dev("stop_inclusive", "transmittance stop at T(1 - alpha) <= 1e-4", "RAS", "PRF-06",
         {"stop_inclusive": True},
         "gsplat 1.5.3 RasterizeToPixels3DGSFwd.cu:154 (`next_T <= 1e-4f`)", None,
         excludes=("stop_off",),
         note="differs only where T(1 - alpha) equals 1e-4 exactly, which the oracle treats as "
              "a near-tie (ORC-04)"),
    _dev("blend_at_cutoff", "the saturating fragment blended, then stop", "RAS", "RAS-05",
         {"transmittance_stop": "after"},
         "the variant discussed in gsplat #556 / PR #541 (HARD-07); the oracle's planted bug (b)",
         _STACK),
    _dev("stop_off", "no transmittance stop", "RAS", "RAS-05", {"transmittance_stop": "off"},
         "every fragment blended (\"break vs continue\", gsplat #556; dense reimplementations)",
         _STACK),
    _dev("no_background", "no background term", "RAS", "RAS-06", {"background_term": False},
         "composited over black whatever the background (the original adds T bg, forward.cu L372)",
         dataclasses.replace(_ROTATED, background=(1.0, 1.0, 1.0)),
         excludes=("background_grad_doubled",)),
    _dev("no_cap_gradient", "no gradient through the alpha cap", "RAS", "PRF-07",
         {"grad_through_alpha_cap": False},
         "gsplat 1.5.3 RasterizeToPixels3DGSBwd.cu:222 (`if (opac * vis <= 0.999f)`)",
         dataclasses.replace(_OPAQUE, backward=True), backward_only=True),
    _dev("background_grad_doubled", "background term counted twice in the backward", "RAS",
         "RAS-07", {"background_grad_factor": 2.0},
         "diff-gaussian-rasterization #86 (the 3dgs_accel branch, HARD-10)",
         dataclasses.replace(_ROTATED, background=(0.9, 0.6, 0.3), backward=True),
         backward_only=True),
    _dev("conic_offdiag_doubled", "conic off-diagonal gradient doubled", "RAS", "RAS-08",
         {"conic_offdiag_grad_factor": 2.0},
         "the -0.5 on dL_dconic2D.y \"fixed\" with the x2 kept (gaussian-splatting #551, HARD-03); "
         "the oracle's planted bug (c)", dataclasses.replace(_ROTATED, backward=True),
         backward_only=True),
    _dev("means2d_grad_ndc", "means2d gradient in NDC units", "API", "API-05",
         {"means2d_grad_units": "ndc"},
         "the original's screen-space gradient is in NDC, pixels times W/2, H/2 (backward.cu "
         "L460-461; HARD-04)", dataclasses.replace(_ROTATED, backward=True), backward_only=True),
]

#: name -> Deviation, in pipeline order
DEVIATIONS: dict[str, Deviation] = {d.name: d for d in _CATALOGUE}

#: the profiles as named combinations: the deviations from the original that make each
PROFILE_CHOICES: dict[str, frozenset] = {
    "inria": frozenset(),
    "gsplat": frozenset({"near_gsplat", "frustum_principal_point", "det_cull_nonpositive",
                         "radius_opacity_aware", "gsplat_tiles", "alpha_cap_0.999",
                         "stop_inclusive", "no_cap_gradient"}),
}


def incompatible(names) -> str | None:
    """Why ``names`` cannot be switched on together (two set one option to different values, or
    one makes another meaningless), or None."""
    names = sorted(names)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            da, db = DEVIATIONS[a], DEVIATIONS[b]
            same = set(da.options()) & set(db.options())
            clash = [k for k in same if da.options()[k] != db.options()[k]]
            if clash:
                return f"{a} and {b} both set {', '.join(sorted(clash))}"
            if b in da.excludes or a in db.excludes:
                return f"{a} makes {b} meaningless"
    return None


def check_deviations(names, where: str = "RenderConfig.deviations") -> frozenset:
    """``names`` as a frozenset of known, compatible deviation names, else ValueError naming
    ``where`` and what was expected (DEV-01)."""
    if isinstance(names, str) or not all(isinstance(n, str) for n in _iterable(names, where)):
        raise ValueError(f"{where}: expected a set of deviation names, got {names!r}")
    names = frozenset(names)
    unknown = sorted(names - set(DEVIATIONS))
    if unknown:
        raise ValueError(f"{where}: expected names from refgs.deviations.DEVIATIONS "
                         f"({', '.join(DEVIATIONS)}), got {', '.join(map(repr, unknown))}")
    why = incompatible(names)
    if why:
        raise ValueError(f"{where}: expected compatible deviations, got {why}")
    return names


def _iterable(names, where):
    try:
        return list(names)
    except TypeError:
        raise ValueError(f"{where}: expected a set of deviation names, got {names!r}") from None


def apply_deviations(profile: Profile, names) -> Profile:
    """``profile`` with the options of every deviation in ``names`` set (DEV-01); ``profile``
    itself, unchanged, when ``names`` is empty."""
    names = check_deviations(names)
    if not names:
        return profile
    changes: dict = {}
    for n in sorted(names):
        changes.update(DEVIATIONS[n].options())
    return dataclasses.replace(profile, **changes)


def label(names) -> str:
    """``{no dilation, no frustum clamp}`` in catalogue order."""
    return "{" + ", ".join(DEVIATIONS[n].label for n in DEVIATIONS if n in set(names)) + "}"


__all__ = ["DEVIATIONS", "PROFILE_CHOICES", "Deviation", "Witness", "apply_deviations",
           "check_deviations", "incompatible", "label"]
