"""gsplat 1.5.3 as an oracle backend: its pure-torch stage functions (CPU), and gsplat.rasterization
where a CUDA device is available (profile "gsplat").

Stage functions (any device, float32 or float64), from ``gsplat.cuda._torch_impl``; the backend
object exposes them as the oracle's ``stage_covariance``, ``stage_projection``, ``stage_sh``:

    covariance_3d(quats, log_scales)             _quat_scale_to_covar_preci   -> Sigma (N,3,3)
    project_gaussians(means, cov3d, camera, ...) _fully_fused_projection      -> means2d, conics,
                                                                                 depths, radii, comp
    eval_sh_colors(means, sh, campos, degree)    _spherical_harmonics (+0.5, clamp at 0 as in
                                                 gsplat rendering.py ``_maybe_evaluate_sh``)

gsplat takes *activated* scales and opacities: log-scales go through exp and logits through the
sigmoid as in refgs.render (numpy ``exp`` for the stage functions; ``torch.exp`` /
``torch.sigmoid`` on the differentiable GPU path; CNV-06, CNV-07).

Where gsplat 1.5.3's pure-torch ``_fully_fused_projection`` differs from its CUDA kernel
(``ProjectionEWA3DGSFused.cu``, which refgs' "gsplat" profile follows):
  * radius: torch uses ceil(3.33 sqrt(Sigma2D_ii)) always; CUDA (called with opacities by
    ``rasterization``) culls o < 1/255 and uses extend = min(3.33, sqrt(2 ln(o / (1/255)))),
    which is < 3.33 for every o < 1 (3.3290 at o = 1), so torch radii are >= CUDA radii;
  * near/far: torch keeps near < z < far (strict); CUDA culls z < near or z > far, so a
    Gaussian at exactly z = near (or far) is kept by CUDA, culled by torch;
  * determinant: torch clamps det >= 1e-10 and never culls on it; CUDA culls det <= 0;
  * ``radius_clip``: not in torch (CUDA culls when both radii <= radius_clip, default 0);
  * culled rows: torch returns computed means2d/depths/conics for every row (radii 0);
    CUDA leaves them 0;
  * antialiasing: both sqrt(max(0, det(Sigma2D) / det(Sigma2D + eps I))) (no 0.005 floor in 1.5.3);
  * gradients: torch autograd differentiates through the frustum clamp exactly (including the
    depth term of the clamped Jacobian), like CUDA's ``persp_proj_vjp``.
Where it differs from refgs beyond that: ``_quat_to_rotmat`` normalises with ``F.normalize``
(eps 1e-12), so a quaternion with |q| < 1e-12 is divided by 1e-12 instead of |q| and Sigma is
wrong (CNV-05, HARD-06; refgs divides by max|q_k| first).
The pure-torch SH constants are Sloan's, written with ~15 significant digits (e.g. 0.48860251190292
vs 0.4886025119029199), and degree-2 uses ``0.946 z^2 - 0.315 = C2[2] (3z^2 - 1)``, equal to
``C2[2] (2z^2 - x^2 - y^2)`` only on the unit sphere: float64 agreement is ~1e-15, not ~1e-16.

``render`` needs CUDA (gsplat's rasterizer is a CUDA extension; on CPU ``_rasterize_to_pixels``
and ``rasterization`` fail, deps.md note 4).  Without it ``unavailable_reason`` says why and
``render`` raises :class:`BackendUnavailable` with that text, and ``has_backward`` is False; a
caller should report render-level checks as n/a with that reason.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

try:
    import torch
    import gsplat
    from gsplat.cuda import _torch_impl as gs
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "oracle.adapters.gsplat_backend needs gsplat 1.5.3 and torch; install the optional "
        "extra (pip install 'refgs[gsplat]': torch==2.13.0 gsplat==1.5.3 packaging)") from exc

from refgs import Gradients, RenderConfig

#: gsplat.rasterization defaults (rendering.py:43-46) = refgs' "gsplat" profile (PRF-01, PRF-03)
NEAR, FAR, EPS2D = 0.01, 1e10, 0.3
#: SH colour offset applied after gsplat's SH, then clamp at 0 (rendering.py:525; CNV-10)
COLOR_OFFSET = 0.5
DTYPES = {"float64": torch.float64, "float32": torch.float32}
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


class BackendUnavailable(RuntimeError):
    """Raised by ``render`` when gsplat's CUDA rasterizer cannot run here (see the message)."""


def _t(x, dtype: str, device="cpu"):
    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected one of {sorted(DTYPES)}, got {dtype!r}")
    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=DTYPES[dtype], device=device)


def _cuda_reason() -> str | None:
    if not torch.cuda.is_available():
        return ("gsplat.rasterization needs a CUDA device (torch.cuda.is_available() is False); "
                "on CPU only gsplat's pure-torch projection and SH stage functions are checked")
    return None


# ---------------------------------------------------------------------------------------------
# stage functions
# ---------------------------------------------------------------------------------------------

def covariance_3d(quats, log_scales, dtype: str = "float32") -> np.ndarray:
    """Sigma (N,3,3) by gsplat's ``_quat_scale_to_covar_preci`` from quats (N,4) wxyz and
    scales exp(log_scales) (N,3) (COV-01)."""
    scales = np.exp(np.asarray(log_scales, np.float64))
    cov, _ = gs._quat_scale_to_covar_preci(_t(quats, dtype), _t(scales, dtype),
                                           compute_covar=True, compute_preci=False, triu=False)
    return cov.numpy()


def project_gaussians(means, cov3d, camera, antialiased: bool = False, dtype: str = "float32",
                      eps2d: float = EPS2D, near: float = NEAR, far: float = FAR) -> dict:
    """gsplat's pure-torch ``_fully_fused_projection`` for one camera (PRJ-01..PRJ-05, PRJ-08).

    means (N,3), cov3d (N,3,3) world space; camera a refgs.Camera.  Returns numpy
    ``means2d`` (N,2), ``conics`` (N,3) (A, B, C), ``depths`` (N,), ``radii`` (N,2) int32
    (torch rule, see the module docstring), ``comp`` (N,) or None.
    """
    w2c = _t(camera.world_to_camera, dtype)[None]
    K = _t(camera.K, dtype)[None]
    radii, m2d, depths, conics, comp = gs._fully_fused_projection(
        _t(means, dtype), _t(cov3d, dtype), w2c, K, int(camera.width), int(camera.height),
        eps2d=eps2d, near_plane=near, far_plane=far, calc_compensations=antialiased)
    return {"means2d": m2d[0].numpy(), "conics": conics[0].numpy(), "depths": depths[0].numpy(),
            "radii": radii[0].numpy(), "comp": None if comp is None else comp[0].numpy()}


def eval_sh_colors(means, sh, campos, degree: int, dtype: str = "float32") -> np.ndarray:
    """max(SH(dir) + 0.5, 0) (N,3) by gsplat's ``_spherical_harmonics`` with dir = mean - campos
    (normalised inside gsplat) (SH-01..SH-03, CNV-10)."""
    dirs = _t(means, dtype) - _t(campos, dtype)
    rgb = gs._spherical_harmonics(int(degree), dirs, _t(sh, dtype))
    return torch.clamp_min(rgb + COLOR_OFFSET, 0.0).numpy()


# ---------------------------------------------------------------------------------------------
# the oracle backend
# ---------------------------------------------------------------------------------------------

@dataclass
class GsplatRenderOutput:
    """Numpy results of gsplat.rasterization; ``graph`` keeps the tensors for the backward.
    gsplat does not expose the per-pixel contributor count: ``n_contrib`` is None."""

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    means2d: np.ndarray
    radii: np.ndarray
    depths: np.ndarray
    conics: np.ndarray
    n_contrib: None = None
    graph: dict = field(repr=False, default_factory=dict)


class GsplatBackend:
    """gsplat 1.5.3 (profile "gsplat", float32).  Stage functions run anywhere (CPU); ``render``
    and ``render_backward`` need CUDA (``unavailable_reason`` is None exactly when they can
    run).  ``device``: None renders on CUDA when present; "cpu" checks the stage functions only;
    "cuda" renders on CUDA or declares why it cannot."""

    name = "gsplat"
    version = gsplat.__version__
    profile = "gsplat"
    dtype = "float32"
    max_sh_degree = 3
    supports_antialiased = True
    supports_opacity_scale = True

    def __init__(self, device: str | None = None):
        if device not in (None, "cpu", "cuda"):
            raise ValueError(f"device: expected 'cpu', 'cuda' or None, got {device!r}")
        self.unavailable_reason = _cuda_reason() if device != "cpu" else (
            "this backend checks gsplat's pure-torch stage functions on the CPU; "
            "gsplat.rasterization is CUDA-only (gsplat_cuda renders with it)")
        self.has_backward = self.unavailable_reason is None
        if device is not None:
            self.name = f"gsplat ({'CUDA' if device == 'cuda' else 'CPU functions'})"

    # ---- stage functions (oracle/protocol.py), gsplat's pure-torch code on CPU ---------------
    def stage_covariance(self, quats, log_scales) -> np.ndarray:
        return covariance_3d(quats, log_scales, self.dtype)

    def stage_projection(self, means, cov3d, opacities, camera, config) -> dict:
        """gsplat's pure-torch projection; ``opacities`` are unused (it has no opacity-aware
        radius, see the module docstring); visible = radii > 0 (gsplat's validity rule)."""
        out = project_gaussians(means, cov3d, camera, bool(config.antialiased), self.dtype)
        out["visible"] = np.any(out["radii"] > 0, axis=-1)
        return out

    def stage_sh(self, means, sh, campos, degree) -> np.ndarray:
        return eval_sh_colors(means, sh, campos, degree, self.dtype)

    def render(self, gaussians, camera, config: RenderConfig | None = None) -> GsplatRenderOutput:
        """gsplat.rasterization(classic or antialiased, packed=False, sh_degree, backgrounds,
        render_mode "RGB+D": the 4th channel is sum_i a_i T_i z_i = refgs' depth)."""
        if self.unavailable_reason:
            raise BackendUnavailable(self.unavailable_reason)
        config = RenderConfig(profile="gsplat") if config is None else config
        if config.profile != "gsplat":
            raise ValueError(f"RenderConfig.profile: gsplat renders only 'gsplat', got {config.profile!r}")
        dev = "cuda"
        p = {f: _t(getattr(gaussians, f), "float32", dev).requires_grad_(True) for f in FIELDS}
        deg = config.active_sh_degree(p["sh"].shape[1])
        opac = torch.sigmoid(p["opacity_logits"])
        if config.opacity_scale is not None:
            opac = opac * _t(config.opacity_scale, "float32", dev)
        colors, alphas, meta = gsplat.rasterization(
            p["means"], p["quats"], torch.exp(p["log_scales"]), opac, p["sh"],
            _t(camera.world_to_camera, "float32", dev)[None], _t(camera.K, "float32", dev)[None],
            int(camera.width), int(camera.height), near_plane=NEAR, far_plane=FAR, eps2d=EPS2D,
            sh_degree=deg, packed=False, backgrounds=_t(config.background, "float32", dev)[None],
            render_mode="RGB+D", rasterize_mode="antialiased" if config.antialiased else "classic")
        means2d = meta["means2d"]
        means2d.retain_grad()
        graph = {"image": colors[0, ..., :3], "alpha": alphas[0, ..., 0], "depth": colors[0, ..., 3],
                 "means2d": means2d, "params": p}
        npy = lambda x: x.detach().cpu().numpy()  # noqa: E731
        return GsplatRenderOutput(image=npy(graph["image"]), alpha=npy(graph["alpha"]),
                                  depth=npy(graph["depth"]), means2d=npy(means2d[0]),
                                  radii=npy(meta["radii"][0]), depths=npy(meta["depths"][0]),
                                  conics=npy(meta["conics"][0]), graph=graph)

    def render_backward(self, out: GsplatRenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
        """Autograd through gsplat's CUDA backward; means2d = dL/d(2D mean) in pixels."""
        if self.unavailable_reason:
            raise BackendUnavailable(self.unavailable_reason)
        g = out.graph
        loss = torch.zeros((), device=g["image"].device)
        for name, v in (("image", v_image), ("alpha", v_alpha), ("depth", v_depth)):
            if v is not None:
                v = np.asarray(v)
                if v.shape != tuple(g[name].shape):
                    raise ValueError(f"v_{name}: expected shape {tuple(g[name].shape)}, got {v.shape}")
                loss = loss + (g[name] * _t(v, "float32", g[name].device)).sum()
        inputs = [g["params"][f] for f in FIELDS] + [g["means2d"]]
        grads = torch.autograd.grad(loss, inputs, retain_graph=True, allow_unused=True) \
            if loss.requires_grad else [None] * len(inputs)
        arrs = [np.zeros(tuple(x.shape), np.float32) if d is None else d.detach().cpu().numpy()
                for x, d in zip(inputs, grads)]
        arrs[-1] = arrs[-1].reshape(-1, 2)        # means2d [1, N, 2] -> (N, 2)
        return Gradients(*arrs)


gsplat_backend = GsplatBackend()
#: pinned: the pure-torch stage functions on the CPU only, or the CUDA rasterizer
gsplat_cpu = GsplatBackend("cpu")
gsplat_cuda = GsplatBackend("cuda")

__all__ = ["GsplatBackend", "GsplatRenderOutput", "BackendUnavailable", "covariance_3d",
           "project_gaussians", "eval_sh_colors", "gsplat_backend", "gsplat_cpu", "gsplat_cuda"]
