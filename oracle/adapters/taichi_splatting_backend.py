"""taichi-splatting 0.13.0 (a Taichi Gaussian-splatting renderer with its own conventions) as an
oracle backend, judged against refgs' "inria" profile, float32 and float64.

Install (the published wheel asks for ``taichi-nightly``, which is not on the index):
``pip install taichi==1.7.4 beartype tqdm tensordict`` then
``pip install --no-deps taichi-splatting==0.13.0``, or ``pip install "refgs[taichi]"`` plus the
second line.

What runs where (found by running it; file:line are in the installed package)
----------------------------------------------------------------------------
* ``import taichi_splatting`` JIT-compiles the CUDA sources of ``cuda_lib`` (radix sort, prefix
  sum; ``cuda_lib/__init__.py:10``) and fails without a CUDA toolkit.  Workaround: without CUDA
  the adapter registers a stand-in module ``taichi_splatting.cuda_lib`` (in ``sys.modules``,
  before the import) whose functions raise :class:`BackendUnavailable`; only the tile mapper
  calls them (``mapper/tile_mapper.py``), which the CPU path never reaches.
* On the CPU (``ti.init(arch=ti.cpu)``) the projection (``perspective.project_to_image``),
  frustum culling (``perspective.frustum_culling``) and SH evaluation (``evaluate_sh_at``) run in
  float32 and float64: they are the backend's ``stage_projection`` and ``stage_sh``.
* The rasterizer needs CUDA: its forward kernel uses block shared memory
  (``rasterizer/forward.py:62-76``; Taichi 1.7.4 on x64: "ti.block.shared_array is not
  supported"), its backward warp intrinsics (``rasterizer/backward.py:212``), and the tile
  mapper the CUDA sort.  ``render``/``render_backward`` are n/a without CUDA
  (``unavailable_reason``).  The float64 render is n/a everywhere: ``encode_depth32`` views the
  depth column as int32 (``misc/encode_depth.py:28``), which torch refuses for float64
  ("self.stride(-1) must be 1 to view Double as Int").
* ``ti.init`` is called by the adapter (taichi-splatting never calls it) before the first kernel
  and again whenever the other dtype's backend is used: CUDA when torch sees a GPU, else the CPU,
  ``default_fp`` the backend's dtype (see :func:`_ensure_taichi`).

Conventions mapped (refgs side: docs/spec/conventions.md)
---------------------------------------------------------
* Parameters: raw, as refgs: ``log_scaling`` (exp), ``alpha_logit`` (sigmoid,
  ``perspective/projection.py:70``), ``rotation`` normalised in the kernel (``:57``).
* Quaternion order: **(x, y, z, w)** -- ``quat_to_mat`` unpacks ``x, y, z, w = q``
  (``taichi_lib/generic.py:342``) although ``data_types.py:39`` documents "quaternion wxyz";
  refgs' (w, x, y, z) is rolled by one (CNV-04).
* Camera: ``CameraParams(T_image_camera=K, T_camera_world=W2C)`` (``perspective/params.py``);
  u = (K t)/t_z (``generic.py:147-148``) honours c_x, c_y; pixels are sampled at centres + 0.5
  (``rasterizer/forward.py:55``), as CNV-08.  near_plane = 0.2 (the inria cull, PRF-01:
  taichi keeps depth > near, ``perspective/culling.py:28``), far_plane = float32 max (the inria
  profile has no far plane), ``blur_cov`` = 0.3 (the dilation, PRJ-04).
* SH: taichi takes (N, 3, K) with K = (degree + 1)^2 exactly (``spherical_harmonics.py:13-20``);
  refgs' (N, K, 3) is transposed and cut to the active degree.  Its view direction is
  **normalize(campos - mean)** (``spherical_harmonics.py:128``; refgs and the original:
  mean - campos, SH-03) and its colour is **clamp(SH + 0.5, 0, 1)** (``:132``; refgs: max(., 0),
  CNV-10).  These are taichi-splatting's conventions; the adapter does not undo them.
* Projection: no frustum clamp in the EWA Jacobian (``generic.py:194-205``; refgs PRJ-03),
  Gaussians culled when the *centre* falls more than ``margin_tiles * tile_size`` = 48 px
  outside the image (``culling.py:28-31``; the inria profile has no such cull).
  ``stage_projection`` receives Sigma (N,3,3) where taichi takes quaternions and log-scales: the
  adapter factors Sigma = R diag(s^2) R^T (numpy ``eigh``, float64) and passes log s and R's
  quaternion; this costs ~eps * cond(Sigma) in Sigma.  ``radii`` are taichi's
  ``compute_radius`` (3 sqrt(lambda_max), ``misc/radius.py:27``, a float) rounded up; taichi's
  tiling uses an oriented 3-sigma box instead (``RasterConfig.tight_culling``).
* Rendering (CUDA only, not run in this session): mirrors ``render_gaussians``
  (``renderer.py:85-114``: cull, SH at the detached means, project, encode depth, rasterize),
  with three feature channels added by the adapter: colour - background (the image is then
  ``raster + background`` = sum w_i c_i + (1 - sum w_i) bg, so the background term is
  differentiable, RAS-06/07), a constant 1 (``alpha`` = sum w_i, differentiable) and the camera
  depth (``depth``).  ``opacity_scale`` multiplies the 2D opacities.  taichi-splatting's own
  ``image_weight`` is non-differentiable (``rasterizer/function.py:66``) and it has no background.
"""
from __future__ import annotations

import sys
import types
from dataclasses import dataclass, field

import numpy as np

try:
    import torch
    import taichi as ti
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "oracle.adapters.taichi_splatting_backend needs taichi 1.7.4, torch and taichi-splatting "
        "0.13.0 (pip install 'refgs[taichi]', then pip install --no-deps taichi-splatting==0.13.0)"
    ) from exc

from refgs import Gradients, RenderConfig, to_activated
from refgs.render import validate_inputs


class BackendUnavailable(RuntimeError):
    """A taichi-splatting stage that cannot run here was called (see the message)."""


CUDA = torch.cuda.is_available()
_CUDA_LIB = "taichi_splatting.cuda_lib"


def _install_cuda_lib_stand_in() -> None:
    """Without CUDA: a ``taichi_splatting.cuda_lib`` whose functions raise (module docstring)."""
    if CUDA or _CUDA_LIB in sys.modules:
        return
    stand_in = types.ModuleType(_CUDA_LIB)

    def unavailable(*_args, **_kwargs):
        raise BackendUnavailable("taichi_splatting.cuda_lib (tile mapping: radix sort, prefix sum) "
                                 "is CUDA-only and no CUDA device is available")

    stand_in.full_cumsum = stand_in.radix_sort_pairs = stand_in.segmented_sort_pairs = unavailable
    sys.modules[_CUDA_LIB] = stand_in


_install_cuda_lib_stand_in()
try:
    import taichi_splatting
    from taichi_splatting import RasterConfig, compute_radius, evaluate_sh_at, perspective, rasterize
    from taichi_splatting.misc.encode_depth import encode_depth
except ImportError as exc:  # pragma: no cover - exercised only without the package
    raise ImportError("oracle.adapters.taichi_splatting_backend needs taichi-splatting 0.13.0 "
                      "(pip install --no-deps taichi-splatting==0.13.0)") from exc

VERSION = "0.13.0"
#: the inria near cull (PRF-01); taichi keeps depth > near_plane (perspective/culling.py:28)
NEAR = 0.2
#: the inria profile has no far plane; CameraParams needs a finite far > near (params.py:74)
FAR = float(np.finfo(np.float32).max)
#: the dilation, CameraParams.blur_cov (params.py:18; PRJ-04)
BLUR = 0.3
#: taichi-splatting's defaults: RasterConfig(tile_size=16, margin_tiles=3, gaussian_scale=3.0)
CONFIG = RasterConfig()
TORCH = {"float32": torch.float32, "float64": torch.float64}
_CPU_REASON = ("taichi-splatting's rasterizer needs CUDA (block shared memory in "
               "rasterizer/forward.py:62-76, warp intrinsics in rasterizer/backward.py:212, the "
               "CUDA sort of cuda_lib) and torch sees no CUDA device; its projection and SH stages "
               "run on the CPU and are checked")
_F64_REASON = ("taichi-splatting renders only float32: encode_depth32 views float64 depths as "
               "int32 (misc/encode_depth.py:28), which torch rejects; its projection and SH stages "
               "run in float64 and are checked")

#: the dtype Taichi was last initialised for (``ti.init``'s ``default_fp``), or None
_TAICHI_FP: list = [None]

_SH_REASON = ("taichi-splatting's SH convention: view direction normalize(campos - mean) "
              "(spherical_harmonics.py:128) and colour clamp(SH + 0.5, 0, 1) (:132); refgs' "
              "deviations sh_dir_reversed + colour_clamp_01 explain every example (SH-03, CNV-10)")
_PROJ_REASON = ("taichi-splatting's projection convention: no frustum clamp in the Jacobian "
                "(taichi_lib/generic.py:194-205), radius 3 sqrt(lambda_max) without the 0.1 floor "
                "(misc/radius.py:27), and a Gaussian is in view when its centre lies within 48 px of "
                "the image (perspective/culling.py:28-31) where inria culls on an empty tile "
                "rectangle; refgs' deviations no_frustum_clamp + radius_3sigma explain all but the "
                "in-view differences (PRJ-03, PRJ-05, PRF-04)")
#: convention differences per dtype (float64's projection also fails by taichi-splatting-1, so it
#: is not declared known: docs/findings/taichi-splatting-1.md)
KNOWN_DIFFERENCES = {
    "float32": ({"check": "stage_sh", "reason": _SH_REASON},
                {"check": "stage_projection", "reason": _PROJ_REASON}),
    "float64": ({"check": "stage_sh", "reason": _SH_REASON},),
}


def _ensure_taichi(dtype: str) -> None:
    """``ti.init`` (CUDA when available, else the CPU) with ``default_fp`` = ``dtype``, again
    whenever the dtype changes.  taichi-splatting's kernels write float literals and take
    ``blur_cov`` as ``ti.f32`` (perspective/projection.py:43), so with Taichi's default f32 its
    float64 kernels compute in part in float32; its own float64 tests initialise Taichi with
    ``default_fp=ti.f64`` (tests/test_rasterizer.py:85), as this adapter does."""
    if _TAICHI_FP[0] != dtype:
        ti.init(arch=ti.cuda if CUDA else ti.cpu, default_fp=ti.f64 if dtype == "float64" else ti.f32,
                log_level=ti.WARN)
        _TAICHI_FP[0] = dtype


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """refgs' scalar-first quaternions (CNV-04) in taichi-splatting's scalar-last order."""
    return np.roll(np.asarray(q), -1, axis=-1)


def factor_covariance(cov3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sigma (N,3,3) = R diag(s^2) R^T -> (unit quaternions (N,4) (w,x,y,z), log s (N,3)), float64.

    R is ``eigh``'s eigenvector matrix with det +1; its quaternion by Shepperd's method."""
    w, V = np.linalg.eigh(np.asarray(cov3d, np.float64))
    V = V * np.where(np.linalg.det(V) < 0, -1.0, 1.0)[:, None, None]
    log_s = 0.5 * np.log(np.maximum(w, np.finfo(np.float64).tiny))
    return _rotation_to_quat(V), log_s


def _rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices (N,3,3) (Shepperd: the largest of
    4w^2, 4x^2, 4y^2, 4z^2 is computed directly, the rest from it)."""
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.diagonal(R, axis1=1, axis2=2)
    cand = np.stack([1 + tr, 1 + 2 * diag[:, 0] - tr, 1 + 2 * diag[:, 1] - tr,
                     1 + 2 * diag[:, 2] - tr], -1)
    k = np.argmax(cand, axis=-1)
    q = np.empty((len(R), 4))
    for i, (r, kk) in enumerate(zip(R, k)):
        s = 2.0 * np.sqrt(max(cand[i, kk], 0.0))
        if kk == 0:
            q[i] = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif kk == 1:
            q[i] = [(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif kk == 2:
            q[i] = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s]
        else:
            q[i] = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4]
    return q


def camera_params(camera, dtype: str, device: str = "cpu"):
    """taichi-splatting's CameraParams for a refgs Camera (module docstring: Camera)."""
    t = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=TORCH[dtype], device=device)  # noqa: E731
    return perspective.CameraParams(
        T_image_camera=t(camera.K), T_camera_world=t(camera.world_to_camera), near_plane=NEAR,
        far_plane=FAR, image_size=(int(camera.width), int(camera.height)), blur_cov=BLUR)


@dataclass
class TaichiRenderOutput:
    """Numpy results of one render (CUDA only); ``graph`` keeps the tensors for the backward."""

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    visible: np.ndarray
    graph: dict = field(repr=False, default_factory=dict)


class TaichiSplattingBackend:
    """taichi-splatting 0.13.0 judged against the inria profile in ``dtype``."""

    name = "taichi-splatting"
    version = VERSION
    profile = "inria"
    max_sh_degree = 3
    supports_antialiased = False
    supports_opacity_scale = True

    def __init__(self, dtype: str, require_cuda: bool = False):
        if dtype not in TORCH:
            raise ValueError(f"dtype: expected one of {sorted(TORCH)}, got {dtype!r}")
        self.dtype = dtype
        self.device = "cuda" if CUDA else "cpu"
        self.unavailable_reason = _F64_REASON if dtype == "float64" else (None if CUDA else _CPU_REASON)
        if require_cuda:
            self.name = "taichi-splatting (CUDA)"
            if not CUDA:
                self.unavailable_reason = "taichi-splatting on CUDA: torch sees no CUDA device here"
        self.has_backward = self.unavailable_reason is None
        self.known_differences = KNOWN_DIFFERENCES[dtype]

    def _t(self, a, requires_grad: bool = False):
        _ensure_taichi(self.dtype)
        x = torch.as_tensor(np.asarray(a, np.float64), dtype=TORCH[self.dtype], device=self.device)
        return x.requires_grad_(requires_grad)

    # ---- stage functions (run on the CPU) -------------------------------------------------------
    def stage_sh(self, means, sh, campos, degree) -> np.ndarray:
        """``evaluate_sh_at`` (SH-01..SH-03; its direction and clamp, module docstring)."""
        k = (int(degree) + 1) ** 2
        params = self._t(np.asarray(sh)[:, :k, :].transpose(0, 2, 1).copy())
        n = len(params)
        idx = torch.arange(n, dtype=torch.int64, device=self.device)
        out = evaluate_sh_at(params, self._t(means), idx, self._t(campos))
        return out.detach().cpu().numpy()

    def stage_projection(self, means, cov3d, opacities, camera, config) -> dict:
        """``perspective.project_to_image`` of every Gaussian and ``perspective.frustum_culling``
        as ``visible`` (renderer.py:147-157); Sigma factored into quaternion and scales."""
        n = len(means)
        quats, log_s = factor_covariance(cov3d)
        o = np.clip(np.asarray(opacities, np.float64), 1e-300, 1 - 1e-16)
        g3 = taichi_splatting.Gaussians3D(
            position=self._t(means), log_scaling=self._t(log_s), rotation=self._t(wxyz_to_xyzw(quats)),
            alpha_logit=self._t(np.log(o / (1 - o))[:, None]), feature=self._t(np.zeros((n, 3))),
            batch_size=(n,))
        cam = camera_params(camera, self.dtype, self.device)
        idx = torch.arange(n, dtype=torch.int64, device=self.device)
        g2d, depth_var = perspective.project_to_image(g3, idx, cam)
        visible = perspective.frustum_culling(g3.position, cam, CONFIG.margin_tiles * CONFIG.tile_size)
        radius = compute_radius(g2d, CONFIG.gaussian_scale).detach().cpu().numpy()
        vis = visible.cpu().numpy()
        r = np.where(vis, np.ceil(radius), 0).astype(np.int32)
        g2d = g2d.detach().cpu().numpy()
        return {"means2d": g2d[:, 0:2], "conics": g2d[:, 2:5],
                "depths": depth_var[:, 0].detach().cpu().numpy(), "radii": np.stack([r, r], -1),
                "visible": vis}

    # ---- rendering (CUDA) ------------------------------------------------------------------------
    def render(self, gaussians, camera, config: RenderConfig | None = None) -> TaichiRenderOutput:
        """render_gaussians' pipeline with the adapter's feature channels (module docstring)."""
        config = RenderConfig() if config is None else config
        validate_inputs(gaussians, camera, config)
        if self.unavailable_reason:
            raise BackendUnavailable(self.unavailable_reason)
        if config.profile != "inria":
            raise ValueError(f"RenderConfig.profile: judged as 'inria' only, got {config.profile!r}")
        to_activated(gaussians)                       # the zero-quaternion check (CNV-05)
        n = len(gaussians)
        deg = config.active_sh_degree(gaussians.sh.shape[1])
        k = (deg + 1) ** 2
        p = {"means": self._t(gaussians.means, True), "log_scales": self._t(gaussians.log_scales, True),
             "quats": self._t(wxyz_to_xyzw(gaussians.quats), True),
             "opacity_logits": self._t(np.asarray(gaussians.opacity_logits)[:, None], True),
             "sh": self._t(np.asarray(gaussians.sh)[:, :k, :].transpose(0, 2, 1).copy(), True)}
        g3 = taichi_splatting.Gaussians3D(position=p["means"], log_scaling=p["log_scales"],
                                          rotation=p["quats"], alpha_logit=p["opacity_logits"],
                                          feature=p["sh"], batch_size=(n,))
        cam = camera_params(camera, self.dtype, self.device)
        mask = perspective.frustum_culling(g3.position, cam, CONFIG.margin_tiles * CONFIG.tile_size)
        idx = torch.nonzero(mask, as_tuple=True)[0]
        colors = evaluate_sh_at(p["sh"], p["means"].detach(), idx, cam.camera_position)
        g2d, depth_var = perspective.project_to_image(g3, idx, cam)
        if config.opacity_scale is not None:
            scale = self._t(config.opacity_scale)[idx]
            g2d = torch.cat([g2d[:, :5], g2d[:, 5:] * scale[:, None]], dim=1)
        g2d.retain_grad()
        bg = self._t(config.background)
        ones = torch.ones_like(depth_var[:, :1])
        feats = torch.cat([colors - bg, ones, depth_var[:, :1]], dim=1).contiguous()
        order = encode_depth(depth_var, depth_range=(cam.near_plane, cam.far_plane))
        raster = rasterize(g2d, order, feats, image_size=cam.image_size, config=CONFIG)
        image = raster.image[..., :3] + bg
        alpha, depth = raster.image[..., 3], raster.image[..., 4]
        npy = lambda x: x.detach().cpu().numpy()  # noqa: E731
        ix = npy(idx)

        def scatter(vals, width):
            out = np.zeros((n, width) if width else (n,), np.dtype(self.dtype))
            out[ix] = vals
            return out

        vis = np.zeros(n, bool)
        vis[ix] = True
        return TaichiRenderOutput(
            image=npy(image), alpha=npy(alpha), depth=npy(depth), means2d=scatter(npy(g2d)[:, 0:2], 2),
            conics=scatter(npy(g2d)[:, 2:5], 3), depths=scatter(npy(depth_var)[:, 0], 0),
            colors=scatter(npy(colors), 3), opacities=scatter(npy(g2d)[:, 5], 0), visible=vis,
            graph={"image": image, "alpha": alpha, "depth": depth, "params": p, "g2d": g2d,
                   "idx": idx, "n": n, "sh_coeffs": int(gaussians.sh.shape[1])})

    def render_backward(self, out: TaichiRenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
        """Autograd through taichi-splatting's kernels; dL/dmeans2d in pixels from the 2D
        Gaussians' uv gradient (its ``viewspace_gradient`` source, renderer.py:169-174)."""
        if self.unavailable_reason:
            raise BackendUnavailable(self.unavailable_reason)
        g = out.graph
        loss = None
        for name, v in (("image", v_image), ("alpha", v_alpha), ("depth", v_depth)):
            if v is None:
                continue
            v = np.asarray(v)
            if v.shape != tuple(g[name].shape):
                raise ValueError(f"v_{name}: expected shape {tuple(g[name].shape)}, got {v.shape}")
            term = (g[name] * self._t(v)).sum()
            loss = term if loss is None else loss + term
        names = ("means", "log_scales", "quats", "opacity_logits", "sh")
        inputs = [g["params"][f] for f in names] + [g["g2d"]]
        grads = torch.autograd.grad(loss, inputs, allow_unused=True)
        arr = [np.zeros(tuple(x.shape), np.dtype(self.dtype)) if d is None else d.detach().cpu().numpy()
               for x, d in zip(inputs, grads)]
        v_m2d = np.zeros((g["n"], 2), np.dtype(self.dtype))
        v_m2d[g["idx"].cpu().numpy()] = arr[5][:, 0:2]
        return Gradients(means=arr[0], log_scales=arr[1], quats=np.roll(arr[2], 1, axis=-1),
                         opacity_logits=arr[3][:, 0], sh=_sh_grad(arr[4], g["sh_coeffs"]),
                         means2d=v_m2d)


def _sh_grad(v_sh_taichi: np.ndarray, n_coeffs: int) -> np.ndarray:
    """(N, 3, k) in taichi's layout -> refgs' (N, K, 3) with K = ``n_coeffs``; coefficients above
    the active degree get exactly zero (SH-01)."""
    v = np.asarray(v_sh_taichi)
    out = np.zeros((v.shape[0], n_coeffs, 3), v.dtype)
    out[:, :v.shape[2], :] = v.transpose(0, 2, 1)
    return out


taichi_float32 = TaichiSplattingBackend("float32")
taichi_float64 = TaichiSplattingBackend("float64")
#: the CUDA renderer only (Taichi picks its device per process: on a machine with CUDA,
#: taichi_float32 renders there too)
taichi_cuda32 = TaichiSplattingBackend("float32", require_cuda=True)

__all__ = ["TaichiSplattingBackend", "TaichiRenderOutput", "BackendUnavailable", "camera_params",
           "factor_covariance", "wxyz_to_xyzw", "taichi_cuda32", "taichi_float32",
           "taichi_float64"]
