"""Every threshold and magic number of the spec, named, with its source and clause id.

Two *profiles* collect the constants where the original 3DGS rasterizer
(graphdeco-inria/diff-gaussian-rasterization @59f5f77, "inria") and gsplat 1.5.3
("gsplat") differ.  Everything that is the same in both lives at module level.
Sources are given as ``repo@commit:path:line`` (or gsplat-1.5.3 wheel path:line).
Clause ids refer to ``docs/spec/*.md``.
"""
from __future__ import annotations

from dataclasses import dataclass

# --------------------------------------------------------------------------------------------
# Shared constants
# --------------------------------------------------------------------------------------------

#: Tile edge in pixels (BLOCK_X = BLOCK_Y = 16, diff-gaussian-rasterization
#: cuda_rasterizer/config.h; gsplat rendering.py:49 ``tile_size: int = 16``).  [RAS-01]
TILE_SIZE = 16

#: Fragments with alpha below this are skipped (forward.cu:342 ``alpha < 1.0f/255.0f``;
#: gsplat Common.h:54 ``ALPHA_THRESHOLD (1.f / 255.f)``).  [RAS-04]
ALPHA_MIN = 1.0 / 255.0

#: Front-to-back compositing stops before T would drop below this
#: (forward.cu:344 ``test_T < 0.0001f``; gsplat RasterizeToPixels3DGSFwd.cu:154 ``next_T <= 1e-4f``).  [RAS-05]
T_MIN = 1e-4

#: Quaternion norms below this are "near-degenerate": an epsilon-guarded normalisation
#: q / max(|q|, eps) -- torch ``F.normalize`` (eps 1e-12) as gsplat's ``_quat_to_rotmat`` uses it
#: (gsplat-1.5.3 cuda/_torch_impl.py) -- no longer returns the direction of q there.  refgs needs no
#: guard (it divides by max|q_k| first, CNV-05); this names the band the tests and the oracle's
#: ``near_degenerate_quaternions`` strategy must reach.  [CNV-05, HARD-06]
QUAT_TINY_NORM = 1e-12

#: Real spherical-harmonics constants (auxiliary.h:21-39; utils/sh_utils.py).  [SH-02]
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
         0.3731763325901154, -0.4570457994644658, 1.445305721320277,
         -0.5900435899266435)
#: Highest SH degree the spec defines (3DGS ``max_sh_degree = 3``).  [SH-01]
SH_MAX_DEGREE = 3
#: Offset added to the SH colour before the clamp at 0 (forward.cu:68 ``result += 0.5f``;
#: gsplat rendering.py:525 ``clamp_min(colors + 0.5, 0.0)``).  [SH-03]
SH_COLOR_OFFSET = 0.5


#: Log-scales above this fraction of log(largest float of the dtype) are rejected by validation:
#: Sigma ~ exp(2 log_s) times (f/z)^2 must stay finite (our choice; ~177 in float64, ~22 in
#: float32, i.e. scales up to 1e77 / 3.6e9 world units).  [API-03]
LOG_SCALE_MAX_FRACTION = 0.25

#: A world-to-camera matrix is accepted as rigid when max|R R^T - I| and |det R - 1| are below
#: this (our choice: loose enough for float32 poses written by COLMAP, tight enough to reject a
#: scale or shear).  Bottom row must be exactly (0, 0, 0, 1).  [CNV-02]
RIGID_TOL = 1e-4

#: Vectorisation chunk: at most this many pixel x Gaussian evaluations are materialised at once
#: in the compositing stage (about 20 float64 arrays of this size are alive: ~0.4 GB).  [RAS-09]
CHUNK_PAIRS = 2_500_000

# --------------------------------------------------------------------------------------------
# Profiles
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Profile:
    """The constants that differ between the original 3DGS and gsplat 1.5.3 (clauses PRF-*).

    Attributes
    ----------
    name: "inria" or "gsplat".
    near: cull threshold on camera depth z.
    near_inclusive: True -> culled when ``z <= near`` (inria), False -> when ``z < near`` (gsplat).
    far: cull when ``z > far`` (``inf`` = no far cull).
    frustum_margin: the EWA Jacobian clamps t.x/t.z to the screen edges widened by this fraction
        of tan(fov/2) (inria: symmetric +-1.3 tan(fov/2); gsplat: ``(W-cx)/fx + 0.3 tan(fov/2)`` and
        ``cx/fx + 0.3 tan(fov/2)``).
    frustum_symmetric: inria ignores cx, cy in the clamp (symmetric limits), gsplat uses them.
    eps2d: low-pass dilation added to both diagonal entries of the 2D covariance.
    radius_rule: "eig" (inria: ceil(3 sqrt(lambda_max)) with the 0.1 floor) or "axis" (gsplat:
        per-axis ceil(extend sqrt(Sigma_ii)), extend = min(3.33, sqrt(2 ln(o / (1/255))))).
    radius_sigma: 3 (inria) or 3.33 (gsplat GAUSSIAN extend).
    eig_floor: inria's floor under mid**2 - det (0.1).
    alpha_max: cap on alpha (0.99 inria, 0.999 gsplat 1.5.3).
    stop_inclusive: inria stops when ``T(1-a) < T_MIN``; gsplat when ``T(1-a) <= T_MIN``.
    grad_through_alpha_cap: inria passes the gradient through the cap; gsplat gives none where
        ``o G > alpha_max``.
    tile_rule: "inria" (getRect, integer pixel centres) or "gsplat" (floor/ceil of (m -+ r)/16).

    The fields after ``opacity_cull`` are the same in both profiles; only a named deviation
    (refgs/deviations.py, docs/spec/deviations.md) changes them:

    quat_order: "wxyz" (CNV-04) or "xyzw" (the quaternion read scalar-last).
    quat_normalization: "exact" (CNV-05), "none" (R(q) of the raw q) or "eps" (q / max(|q|, 1e-12)).
    rotation_transposed: Sigma built from R^T instead of R (COV-01).
    frustum_clamp: the Jacobian's clamp of t.x/t.z, t.y/t.z (PRJ-03).
    clamp_in_backward: the backward treats a clamped axis as constant (PRJ-07 step 3).
    exact_clamp_depth_grad: the depth gradient of a clamped axis is exact (PRJ-07; False: #75).
    sh_dir_reversed: the SH view direction is camera minus mean (SH-03).
    colour_max: upper clamp of the SH colour (CNV-10: none, ``inf``).
    pixel_offset: pixel (i, j) is sampled at (j + offset, i + offset) (CNV-08: 0.5).
    alpha_skip: fragments with alpha < 1/255 are skipped (RAS-04).
    transmittance_stop: "before" (RAS-05: the saturating fragment is not blended), "after" (it
        is blended, then the pixel stops) or "off" (every fragment is blended).
    background_term: the image adds T_final * background (RAS-06).
    background_grad_factor: times the background term is counted in the backward (RAS-07: 1).
    conic_offdiag_grad_factor: factor on dL/dB handed to the projection backward (RAS-08: 1).
    means2d_grad_units: "pixels" (API-05) or "ndc" (the original's: pixels times W/2, H/2).
    """

    name: str
    near: float
    near_inclusive: bool
    far: float
    frustum_margin: float
    frustum_symmetric: bool
    eps2d: float
    radius_rule: str
    radius_sigma: float
    eig_floor: float
    alpha_max: float
    stop_inclusive: bool
    grad_through_alpha_cap: bool
    tile_rule: str
    det_cull_nonpositive: bool
    offscreen_cull: bool
    opacity_cull: bool
    quat_order: str = "wxyz"
    quat_normalization: str = "exact"
    rotation_transposed: bool = False
    frustum_clamp: bool = True
    clamp_in_backward: bool = True
    exact_clamp_depth_grad: bool = True
    sh_dir_reversed: bool = False
    colour_max: float = float("inf")
    pixel_offset: float = 0.5
    alpha_skip: bool = True
    transmittance_stop: str = "before"
    background_term: bool = True
    background_grad_factor: float = 1.0
    conic_offdiag_grad_factor: float = 1.0
    means2d_grad_units: str = "pixels"


#: The original 3DGS rasterizer (diff-gaussian-rasterization@59f5f77).
INRIA = Profile(
    name="inria",
    near=0.2,                    # auxiliary.h:154 in_frustum: p_view.z <= 0.2f   [PRF-01]
    near_inclusive=True,
    far=float("inf"),            # no far cull in the rasterizer                    [PRF-01]
    frustum_margin=0.3,          # forward.cu:81-82 limx = 1.3f * tan_fovx          [PRF-02]
    frustum_symmetric=True,
    eps2d=0.3,                   # forward.cu:110-111 cov[0][0] += 0.3f             [PRF-03]
    radius_rule="eig",           # forward.cu:229-232                               [PRF-04]
    radius_sigma=3.0,
    eig_floor=0.1,               # forward.cu:230 max(0.1f, mid*mid - det)
    alpha_max=0.99,              # forward.cu:341 min(0.99f, ...)                   [PRF-05]
    stop_inclusive=False,        # forward.cu:344 test_T < 0.0001f                  [PRF-06]
    grad_through_alpha_cap=True,  # backward.cu render: no gating on the clamp     [PRF-07]
    tile_rule="inria",           # auxiliary.h:46-56 getRect                        [PRF-08]
    det_cull_nonpositive=False,  # forward.cu:221 `if (det == 0.0f) return;`       [PRF-03]
    offscreen_cull=False,        # empty getRect drops the Gaussian                 [PRF-08]
    opacity_cull=False,
)

#: gsplat 1.5.3 (the version pinned in pyproject's gsplat extra), classic rasterize_mode.
GSPLAT = Profile(
    name="gsplat",
    near=0.01,                   # rendering.py:43; ProjectionEWA3DGSFused.cu:72 z < near_plane  [PRF-01]
    near_inclusive=False,
    far=1e10,                    # rendering.py:44; ProjectionEWA3DGSFused.cu:72 z > far_plane
    frustum_margin=0.3,          # Utils.cuh:514-519 lim_x_pos = (W-cx)/fx + 0.3f*tan_fovx   [PRF-02]
    frustum_symmetric=False,
    eps2d=0.3,                   # rendering.py:46; Utils.cuh:381-388 add_blur      [PRF-03]
    radius_rule="axis",          # ProjectionEWA3DGSFused.cu:164-184                [PRF-04]
    radius_sigma=3.33,
    eig_floor=0.0,
    alpha_max=0.999,             # RasterizeToPixels3DGSFwd.cu:148 min(0.999f, ...) [PRF-05]
    stop_inclusive=True,         # RasterizeToPixels3DGSFwd.cu:154 next_T <= 1e-4f  [PRF-06]
    grad_through_alpha_cap=False,  # RasterizeToPixels3DGSBwd.cu:222 if (opac*vis <= 0.999f) [PRF-07]
    tile_rule="gsplat",          # IntersectTile.cu:62-77 floor/ceil               [PRF-08]
    det_cull_nonpositive=True,   # ProjectionEWA3DGSFused.cu:155 det <= 0.f          [PRF-03]
    offscreen_cull=True,         # ProjectionEWA3DGSFused.cu:193-194                 [PRF-08]
    opacity_cull=True,           # ProjectionEWA3DGSFused.cu:171 opacity < ALPHA_THRESHOLD [PRF-04]
)

PROFILES = {"inria": INRIA, "gsplat": GSPLAT}


def get_profile(name: str) -> Profile:
    """Return the named profile; ValueError naming the valid choices otherwise."""
    try:
        return PROFILES[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"RenderConfig.profile: expected one of {sorted(PROFILES)}, got {name!r}"
        ) from None
