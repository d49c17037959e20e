"""render() and render_backward(): the stages composed -- the public face of the spec.

    Gaussians --covariance--> Sigma --projection--> (means2d, conic, radius, depth)
              --sh--> colours --rasterize--> image, alpha, depth

Spec: docs/spec/stages.md (API-01..API-06) and the stage clauses cited in each module.
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit

from .constants import LOG_SCALE_MAX_FRACTION, RIGID_TOL, Profile, get_profile
from .covariance import covariance_3d, covariance_3d_backward
from .deviations import apply_deviations
from .projection import project_gaussians, project_gaussians_backward
from .rasterize import build_tile_lists, composite, composite_backward
from .sh import eval_sh_colors, eval_sh_colors_backward, num_sh_coeffs
from .types import Camera, Gaussians, Gradients, RenderConfig, RenderOutput


def input_error(field: str, expected: str, got) -> None:
    raise ValueError(f"{field}: expected {expected}, got {got}")


def _as_float_array(field: str, value, expected: str) -> np.ndarray:
    """``value`` as a float64 array, or ValueError naming ``field`` (non-numeric input)."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        input_error(field, expected, repr(value))


def resolve_profile(config: RenderConfig) -> Profile:
    """The Profile named by ``config.profile`` (a Profile instance is accepted as is), with the
    options of ``config.deviations`` set (DEV-01; the profile itself when there are none)."""
    profile = config.profile if isinstance(config.profile, Profile) else get_profile(config.profile)
    return apply_deviations(profile, config.deviations)


def _all_finite(arr: np.ndarray) -> bool:
    """np.all(np.isfinite(arr)), usually without its temporary: a NaN or an infinity anywhere
    makes the sum non-finite, so a finite sum proves every value finite; a non-finite sum (which
    huge finite values can also give) falls back to the exact test."""
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(arr)):
            return True
    return bool(np.all(np.isfinite(arr)))


def validate_gaussians(g: Gaussians) -> None:
    """Raise ValueError naming the field and what was expected (API-03, CNV-05, CNV-11)."""
    if not isinstance(g, Gaussians):
        input_error("gaussians", "a refgs.Gaussians", type(g).__name__)
    n = g.means.shape[0] if g.means.ndim == 2 else -1
    shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
    for name, shape in shapes.items():
        arr = getattr(g, name)
        if arr.shape != shape or n < 0:
            input_error(f"Gaussians.{name}", f"shape {('N',) + shape[1:]} with N = {max(n, 0)}", arr.shape)
    if g.sh.ndim != 3 or g.sh.shape[0] != n or g.sh.shape[2] != 3 or g.sh.shape[1] < 1:
        input_error("Gaussians.sh", f"shape (N, K, 3) with N = {n}, K >= 1", g.sh.shape)
    dtypes = {name: getattr(g, name).dtype for name in Gaussians.FIELDS}
    if len(set(dtypes.values())) != 1:
        input_error("Gaussians", "all five fields in one dtype (float32 or float64)",
              {k: str(v) for k, v in dtypes.items()})
    for name in Gaussians.FIELDS:
        arr = getattr(g, name)
        if not _all_finite(arr):
            bad = np.argwhere(~np.isfinite(arr))[0]
            input_error(f"Gaussians.{name}", "finite values", f"{arr[tuple(bad)]} at index {tuple(int(i) for i in bad)}")
    if n > 0:
        lim = LOG_SCALE_MAX_FRACTION * np.log(np.finfo(g.log_scales.dtype).max)
        if np.any(g.log_scales > lim):
            input_error("Gaussians.log_scales", f"values <= {lim:.1f} (larger scales overflow the covariance "
                  f"in {g.log_scales.dtype})", float(g.log_scales.max()))
        q = g.quats                     # column by column: np.any along a length-4 axis is slow
        zero = (q[:, 0] == 0) & (q[:, 1] == 0) & (q[:, 2] == 0) & (q[:, 3] == 0)
        if np.any(zero):
            input_error("Gaussians.quats", "non-zero quaternions (w, x, y, z) (CNV-05)",
                  f"a zero quaternion at row {int(np.flatnonzero(zero)[0])}")


def validate_inputs(g: Gaussians, camera: Camera, config: RenderConfig) -> None:
    """Raise ValueError naming the field and what was expected (API-03)."""
    validate_gaussians(g)
    if not isinstance(camera, Camera):
        input_error("camera", "a refgs.Camera", type(camera).__name__)
    if not isinstance(config, RenderConfig):
        input_error("config", "a refgs.RenderConfig", type(config).__name__)
    n = g.means.shape[0]
    # camera
    W2C = _as_float_array("Camera.world_to_camera", camera.world_to_camera, "a finite (4, 4) matrix")
    if W2C.shape != (4, 4) or not np.all(np.isfinite(W2C)):
        input_error("Camera.world_to_camera", "a finite (4, 4) matrix", W2C.shape)
    R = W2C[:3, :3].astype(np.float64)
    if not np.array_equal(W2C[3], [0, 0, 0, 1]) or \
            np.max(np.abs(R @ R.T - np.eye(3))) > RIGID_TOL or abs(np.linalg.det(R) - 1) > RIGID_TOL:
        input_error("Camera.world_to_camera", "a rigid transform [[R, t], [0, 0, 0, 1]] with R a rotation "
              f"(R R^T = I, det R = 1 within {RIGID_TOL})", "a non-rigid matrix")
    K = _as_float_array("Camera.K", camera.K, "a finite (3, 3) intrinsics matrix")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        input_error("Camera.K", "a finite (3, 3) intrinsics matrix", K.shape)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        input_error("Camera.K", "positive focal lengths fx = K[0,0], fy = K[1,1]", (K[0, 0], K[1, 1]))
    for name in ("width", "height"):
        v = getattr(camera, name)
        if not isinstance(v, (int, np.integer)) or v <= 0:
            input_error(f"Camera.{name}", "a positive integer", v)
    # config
    resolve_profile(config)
    bg = _as_float_array("RenderConfig.background", config.background, "3 finite values")
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        input_error("RenderConfig.background", "3 finite values", config.background)
    if config.sh_degree is not None and (isinstance(config.sh_degree, bool)
                                         or not isinstance(config.sh_degree, (int, np.integer))):
        input_error("RenderConfig.sh_degree", "None or an integer in 0..3", repr(config.sh_degree))
    deg = config.active_sh_degree(g.sh.shape[1])
    if not 0 <= deg <= 3:
        input_error("RenderConfig.sh_degree", "an integer in 0..3", config.sh_degree)
    if g.sh.shape[1] < num_sh_coeffs(deg):
        input_error("Gaussians.sh", f"K >= {num_sh_coeffs(deg)} coefficients for sh_degree {deg}", g.sh.shape)
    if config.antialiased and resolve_profile(config).name != "gsplat":
        input_error("RenderConfig.antialiased", "False unless profile is 'gsplat'", True)
    if config.opacity_scale is not None:
        s = _as_float_array("RenderConfig.opacity_scale", config.opacity_scale,
                            f"None or ({n},) finite non-negative values")
        if s.shape != (n,) or not np.all(np.isfinite(s)) or np.any(s < 0):
            input_error("RenderConfig.opacity_scale", f"None or ({n},) finite non-negative values", s.shape)


def render(gaussians: Gaussians, camera: Camera, config: RenderConfig | None = None) -> RenderOutput:
    """Render N Gaussians into ``camera`` (all forward clauses; API-04, API-06).

    Computation happens in the Gaussians' dtype (CNV-11).  Returns a RenderOutput whose fields
    are documented in refgs.types; its ``cache`` holds the stage intermediates the backward reads.
    """
    config = RenderConfig() if config is None else config
    validate_inputs(gaussians, camera, config)
    profile = resolve_profile(config)
    g = gaussians
    dt = g.means.dtype
    W, H = int(camera.width), int(camera.height)
    if config.sh_degree is not None and (isinstance(config.sh_degree, bool)
                                         or not isinstance(config.sh_degree, (int, np.integer))):
        input_error("RenderConfig.sh_degree", "None or an integer in 0..3", repr(config.sh_degree))
    deg = config.active_sh_degree(g.sh.shape[1])

    cov = covariance_3d(g.quats, g.log_scales, profile)                         # COV-01
    o_sig = expit(g.opacity_logits)                                # CNV-07
    scale = np.ones_like(o_sig) if config.opacity_scale is None \
        else np.asarray(config.opacity_scale, dt)
    proj = project_gaussians(g.means, cov["cov3d"], o_sig * scale, camera, profile,
                             antialiased=config.antialiased)                   # PRJ-*
    campos = camera.center.astype(dt)
    sh = eval_sh_colors(g.means, g.sh, campos, deg, profile)                   # SH-*
    opac = o_sig * scale * proj["comp"]
    g2d = {"means2d": proj["means2d"], "conics": proj["conics"], "opacities": opac,
           "colors": sh["colors"], "depths": proj["depths"]}
    lists = build_tile_lists(proj["tile_rect"], proj["depths"], proj["visible"], W, H)  # RAS-01/02
    bg = np.asarray(config.background, dt)
    comp = composite(g2d, lists, W, H, profile, bg)                            # RAS-03..06
    return RenderOutput(
        image=comp["image"], alpha=comp["alpha"], depth=comp["depth"],
        n_contrib=comp["n_contrib"], radii=proj["radii"], means2d=proj["means2d"],
        depths=proj["depths"], conics=proj["conics"], cov2d=proj["cov2d"], colors=sh["colors"],
        opacities=opac, final_T=comp["final_T"], visible=proj["visible"], gaussians=g,
        camera=camera, config=config,
        cache={"cov": cov, "proj": proj, "sh": sh, "lists": lists, "o_sig": o_sig,
               "scale": scale, "profile": profile, "g2d": g2d, "sh_degree": deg},
    )


def check_cotangent(name: str, v, shape, dt):
    if v is None:
        return None
    v = np.asarray(v)
    if v.shape != shape or not np.all(np.isfinite(v)):
        input_error(name, f"finite values of shape {shape}", v.shape)
    return v.astype(dt, copy=False)


def render_backward(out: RenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
    """Hand-derived gradient of a scalar loss L through ``render`` (API-05; COV-02, PRJ-07, SH-04, RAS-07).

    v_image (H,W,3) = dL/dimage, optional v_alpha (H,W) = dL/dalpha and v_depth (H,W) = dL/ddepth.
    Returns dL/d(raw parameters) and dL/dmeans2d (pixels) in the dtype of ``out``.  Culled
    Gaussians get zero gradients; SH coefficients above the active degree get zero.
    """
    c = out.cache
    g, cam = out.gaussians, out.camera
    dt = out.image.dtype
    H, W = out.alpha.shape
    v_image = check_cotangent("v_image", v_image, (H, W, 3), dt)
    if v_image is None:
        input_error("v_image", f"an array of shape {(H, W, 3)}", None)
    v_alpha = check_cotangent("v_alpha", v_alpha, (H, W), dt)
    v_depth = check_cotangent("v_depth", v_depth, (H, W), dt)
    profile = c["profile"]
    bg = np.asarray(out.config.background, dt)
    vc = composite_backward(c["g2d"], c["lists"], W, H, profile, bg, out.final_T,
                            v_image, v_alpha, v_depth)
    proj = c["proj"]
    vis = proj["visible"]
    # opacity used = sigmoid(logit) * scale * comp
    v_opac = np.where(vis, vc["v_opacities"], 0)
    o_sig, scale = c["o_sig"], c["scale"]
    v_o_sig = v_opac * scale * proj["comp"]
    v_comp = v_opac * o_sig * scale if out.config.antialiased else None
    v_logits = v_o_sig * o_sig * (1 - o_sig)
    v_sh, v_means_sh = eval_sh_colors_backward(c["sh"], g.sh, np.where(vis[:, None], vc["v_colors"], 0))
    v_means2d = np.where(vis[:, None], vc["v_means2d"], 0)
    v_means, v_cov3d = project_gaussians_backward(proj, cam, v_means2d, vc["v_conics"],
                                                  vc["v_depths"], v_comp)
    v_quats, v_log_scales = covariance_3d_backward(c["cov"], v_cov3d)
    if profile.means2d_grad_units == "ndc":      # deviation means2d_grad_ndc (HARD-04)
        v_means2d = v_means2d * np.asarray([W / 2, H / 2], dt)
    return Gradients(means=v_means + v_means_sh, log_scales=v_log_scales, quats=v_quats,
                     opacity_logits=v_logits, sh=v_sh, means2d=v_means2d)
