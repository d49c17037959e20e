"""gswarp 1.1.0 (a pure-Python NVIDIA Warp port of the original 3DGS rasterizer,
diff_gaussian_rasterization's interface) as an oracle backend: profile "inria", float32.

Install: ``pip install "torch==2.13.0+cpu" gswarp==1.1.0`` (pulls warp-lang; with torch pinned
nothing else changes), or ``pip install "refgs[gswarp]"``.

Entry point and the CPU workaround
----------------------------------
The public entry is ``gswarp.GaussianRasterizer(settings)(means3D=..., ...)``, which calls
``gswarp.rasterizer.rasterize_gaussians``: ``validate_rasterizer_inputs``, then
``standard_autograd.rasterize_gaussians(plan, ...)`` (``gswarp/rasterizer.py:28-57``).  The
validation rejects any tensor that is not on a CUDA device (``_internal/api/validation.py:61``),
although Warp itself has a CPU device.  Where CUDA is available the adapter calls the public
``GaussianRasterizer``; on the CPU it makes the same call the public function makes after its
validation, ``gswarp._internal.frontend.standard_autograd.rasterize_gaussians(plan, ...)`` with
``plan = common.plan_for(gswarp.methods.baseline_3dgs.METHOD)``, and validates the inputs itself
with ``refgs.render.validate_inputs`` (API-03).  gswarp's own validation checks shapes, dtype and
device, and finiteness only with ``debug=True`` (validation.py:148-159).

Second workaround: gswarp's render and backward kernels are *tile* kernels that assume a block of
256 (forward, ``render_ops.py:73-75``) or 32 (backward, ``backward_ops.py:282-284``) cooperating
threads (``wp.tile`` / ``wp.tile_extract`` over the block, ``render_kernels.py:101-116``).  On the
CPU Warp resolves every ``block_dim`` to 1 unless ``warp.config.enable_cpu_blocks`` is True
(warp 1.19 ``config.py:252``, ``_src/context.py:11923``), so each pixel would read one Gaussian
slot per batch and index a one-element tile out of range.  The adapter sets
``warp.config.enable_cpu_blocks = True`` (Warp's cooperative CPU fibers, "experimental" in Warp)
before gswarp's first launch, which reproduces the GPU's block semantics (without it the image
is off by up to 0.34 on a 6-Gaussian scene).  On import it raises ``warp.config.log_level`` to
warnings, and it passes ``auto_tune_verbose=False``, so that Warp and gswarp print no banner or
module-load lines.

The first call compiles gswarp's Warp modules for the CPU (about 90 s on 2 cores; cached in
Warp's kernel cache, ``~/.cache/warp``, afterwards).

Conventions mapped (refgs side: docs/spec/conventions.md)
---------------------------------------------------------
* Parameters: gswarp takes activated ones, like the original's ``GaussianModel`` (``get_scaling``
  = exp, ``get_opacity`` = sigmoid, ``get_rotation`` = normalize, peers: 3DGS
  ``scene/gaussian_model.py``); the kernels do not normalise the quaternion
  (``preprocess_kernels.py:151-165`` reads ``q[0]`` as the real part, order (w, x, y, z), the
  same as refgs, CNV-04).  The adapter passes ``refgs.to_activated`` values computed in float64
  and rounded once to float32, and maps gradients back with ``refgs.raw_gradients``
  (``quats_were_unit=True``).  ``opacity_scale`` multiplies the activated opacity (API-02).
* Camera: ``viewmatrix`` = W2C^T and ``projmatrix`` = (P W2C)^T (the original's
  ``world_view_transform`` / ``full_proj_transform``, row-vector convention; gswarp reads
  ``view_flat[2], [6], [10], [14]`` as row 2 of W2C, ``preprocess_kernels.py:134``);
  ``tanfovx = W / (2 fx)``, ``tanfovy = H / (2 fy)`` (gswarp: ``focal_x = W / (2 tanfovx)``,
  ``preprocess_ops.py:362-363``); ``campos`` = -R^T t (the original's ``camera_center``).
* Principal point and pixel centres: gswarp maps NDC to pixels with ``((v + 1) S - 1) / 2``
  (``math_kernels.py:86-87``) and samples pixel (i, j) at (j, i) (``render_kernels.py:65-66``), the
  original's integer-centred frame.  The adapter's P has P[0,0] = 2 fx / W,
  P[0,2] = 2 cx / W - 1, P[1,1] = 2 fy / H, P[1,2] = 2 cy / H - 1, P[3,2] = 1 (w = z; row 2 is the
  original's ``getProjectionMatrix`` depth row with znear 0.01, zfar 100, unread by gswarp's
  forward), so gswarp's coordinate is u - 0.5 with u = fx x / z + cx: pixel j is sampled at
  u = j + 0.5 (CNV-08), and an off-centre principal point is honoured (the inria profile's one
  extension, PRF-02).  ``means2d`` = gswarp's ``proj_2D`` + 0.5; dL/d(means2d) in pixels =
  gswarp's ``means2D.grad[:, :2]`` (NDC, scaled by W/2 and H/2, ``backward_kernels.py:597-598``)
  divided by (W/2, H/2).
* SH: (N, K, 3) as refgs (the original's ``get_features`` = cat(dc, rest)); view direction
  normalize(mean - campos); colour max(SH + 0.5, 0) (``preprocess_kernels.py:284-335``; CNV-09,
  CNV-10); degree = ``config.active_sh_degree(K)``.
* Background: ``bg`` (3,), added with the final transmittance (``render_kernels.py:143``, RAS-06).
* Outputs: image = color (3,H,W) transposed; ``alpha`` = the accumulated weight sum a_i T_i
  (``render_kernels.py:146``); ``depth`` = sum a_i T_i z_i (``:147``, GSWARP_COMPUTE_DEPTH
  default on); ``radii`` (N,) (the oracle repeats it per axis); ``conics`` = ``conic_2D`` (A, B, C).
  Per-Gaussian depths, colours and ``n_contrib`` are not public outputs: not provided.

Where gswarp differs from the original it ports (and from refgs' inria profile)
-------------------------------------------------------------------------------
* determinant cull |det| <= 1e-7 (``preprocess_kernels.py:222``, ``constants.py:38``) instead of
  det == 0 (PRF-03); det >= 0.09 in exact arithmetic, so only rounding artefacts differ;
* the backward recovers T_final as 1 - alpha (``backward_kernels.py:607``) instead of storing it,
  and divides by max(1 - alpha, 1e-5) (``:649``): gradients on nearly opaque pixels lose
  precision (docs/findings/gswarp-1.md; fails backward_alpha_cap, hard_07, hard_08).

Like the original, it keeps the depth term of the clamped Jacobian (diff-gaussian-rasterization
#75), which refgs does not (PRJ-07): ``known_differences`` declares the three checks this fails.

Capabilities: profile "inria" only (gsplat profile n/a), float32 only (gswarp requires float32,
``validation.py:31``), SH degree <= 3, no antialiasing (gswarp "accepts but does not apply" it).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

try:
    import torch
    import warp as wp
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)   # before Warp's banner
    import gswarp
    from gswarp import GaussianRasterizationSettings, GaussianRasterizer
    from gswarp._internal.frontend import common as gswarp_common
    from gswarp._internal.frontend import standard_autograd
    from gswarp.methods.baseline_3dgs import METHOD as BASELINE_3DGS
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "oracle.adapters.gswarp_backend needs gswarp 1.1.0 and torch; install the optional extra "
        "(pip install 'refgs[gswarp]', i.e. torch==2.13.0 gswarp==1.1.0 warp-lang)") from exc

from refgs import Gradients, RenderConfig, raw_gradients, to_activated
from refgs.render import validate_inputs

#: the original 3DGS camera's projection-matrix depth row (scene/cameras.py znear, zfar); gswarp's
#: forward reads only rows 0, 1 and 3 of the full projection
ZNEAR, ZFAR = 0.01, 100.0
#: gswarp's pixel frame is the original's integer-centred one (math_kernels.py:86-87): refgs'
#: u (pixel j sampled at j + 0.5, CNV-08) is gswarp's coordinate + 0.5
PIXEL_CENTRE = 0.5
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")
#: the original rasterizer's depth gradient under the frustum clamp, which gswarp ports
#: (backward_kernels.py:215, the clamped tx in 2 j02 dL/dJ02); refgs does not reproduce it (PRJ-07)
ISSUE_75 = "https://github.com/graphdeco-inria/diff-gaussian-rasterization/issues/75"
_CLAMP_REASON = ("gswarp ports the original rasterizer's backward under the frustum clamp: the "
                 "depth term 2 fx tx / tz^3 is kept with the clamped tx (backward_kernels.py:215), "
                 "refgs' deviation clamp_depth_grad_original; refgs gives the exact gradient (PRJ-07)")
#: failures of the original's convention, confirmed by oracle.diagnose (docs/conformance.md)
KNOWN_DIFFERENCES = tuple({"check": c, "reason": _CLAMP_REASON, "link": ISSUE_75}
                          for c in ("backward_frustum_clamp", "hard_01", "hard_05"))


def _device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def _enable_cpu_tiles() -> None:
    """Warp's cooperative CPU blocks, so that gswarp's tile kernels see their block (module
    docstring); must precede gswarp's first kernel launch in the process."""
    wp.config.enable_cpu_blocks = True


def camera_settings(camera, background, sh_degree: int, device: str = "cpu") -> GaussianRasterizationSettings:
    """gswarp's ``GaussianRasterizationSettings`` for a refgs Camera (module docstring: Camera,
    Principal point).  Matrices are composed in float64 and rounded once to float32."""
    W2C = np.asarray(camera.world_to_camera, np.float64)
    K = np.asarray(camera.K, np.float64)
    W, H = int(camera.width), int(camera.height)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    P = np.zeros((4, 4))
    P[0, 0], P[0, 2] = 2.0 * fx / W, 2.0 * cx / W - 1.0
    P[1, 1], P[1, 2] = 2.0 * fy / H, 2.0 * cy / H - 1.0
    P[2, 2], P[2, 3] = ZFAR / (ZFAR - ZNEAR), -ZFAR * ZNEAR / (ZFAR - ZNEAR)
    P[3, 2] = 1.0
    R, t = W2C[:3, :3], W2C[:3, 3]

    def f32(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)

    return GaussianRasterizationSettings(
        image_height=H, image_width=W, tanfovx=float(W / (2.0 * fx)),
        tanfovy=float(H / (2.0 * fy)), bg=f32(np.asarray(background, np.float64)),
        scale_modifier=1.0, viewmatrix=f32(W2C.T), projmatrix=f32((P @ W2C).T),
        sh_degree=int(sh_degree), campos=f32(-R.T @ t), prefiltered=False, debug=False,
        antialiasing=False, auto_tune=True, auto_tune_verbose=False)


@dataclass
class GswarpRenderOutput:
    """Numpy results of one gswarp forward; ``graph`` keeps the tensors for the backward."""

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    radii: np.ndarray
    means2d: np.ndarray
    conics: np.ndarray
    visible: np.ndarray
    graph: dict = field(repr=False, default_factory=dict)


class GswarpBackend:
    """gswarp 1.1.0, profile "inria", float32; ``device`` "cuda", "cpu" (Warp's CPU device) or
    None (CUDA when present, else the CPU).  A CUDA backend without a CUDA device declares
    ``unavailable_reason`` (its render-level checks are n/a)."""

    name = "gswarp"
    version = gswarp.__version__
    profile = "inria"
    dtype = "float32"
    max_sh_degree = 3
    supports_antialiased = False
    supports_opacity_scale = True
    has_backward = True
    unavailable_reason = None
    known_differences = KNOWN_DIFFERENCES

    def __init__(self, device: str | None = None):
        if device not in (None, "cpu", "cuda"):
            raise ValueError(f"device: expected 'cpu', 'cuda' or None, got {device!r}")
        self.device = device or _device()
        if self.device == "cuda" and not torch.cuda.is_available():
            self.unavailable_reason = "gswarp on CUDA: torch sees no CUDA device here"
            self.has_backward = False
        if device is not None:
            self.name = f"gswarp ({device.upper() if device == 'cuda' else 'CPU'})"
        if self.device == "cpu":
            _enable_cpu_tiles()

    def _rasterize(self, settings, tensors: dict):
        """The public ``GaussianRasterizer`` on CUDA; on the CPU the call it makes after its
        CUDA-only validation (module docstring)."""
        kw = dict(means3D=tensors["means"], means2D=tensors["means2d"], opacities=tensors["opacities"],
                  shs=tensors["sh"], scales=tensors["scales"], rotations=tensors["quats"])
        if self.device != "cpu":
            color, radii, meta = GaussianRasterizer(settings)(**kw)
            return color, radii, (meta.depth, meta.alpha, meta.proj_2D, meta.conic_2D)
        empty = torch.Tensor([])
        out = standard_autograd.rasterize_gaussians(
            gswarp_common.plan_for(BASELINE_3DGS), kw["means3D"], kw["means2D"], kw["shs"], empty,
            kw["opacities"], kw["scales"], kw["rotations"], empty, settings)
        color, radii, depth, alpha, proj, conic, _ = out
        return color, radii, (depth, alpha, proj, conic)

    def render(self, gaussians, camera, config: RenderConfig | None = None) -> GswarpRenderOutput:
        """gswarp's forward on the scene (module docstring for every mapping)."""
        config = RenderConfig() if config is None else config
        validate_inputs(gaussians, camera, config)
        if config.profile != "inria":
            raise ValueError(f"RenderConfig.profile: gswarp renders only 'inria', got {config.profile!r}")
        act = to_activated(gaussians.astype("float64"))
        opac = act["opacities"]
        if config.opacity_scale is not None:
            opac = opac * np.asarray(config.opacity_scale, np.float64)
        n = len(gaussians)
        dev = self.device

        def f32(a):
            return torch.as_tensor(np.asarray(a, np.float64), dtype=torch.float32, device=dev)

        tensors = {"means": f32(act["means"]), "scales": f32(act["scales"]), "quats": f32(act["quats"]),
                   "opacities": f32(opac.reshape(n, 1)), "sh": f32(act["sh"]),
                   "means2d": torch.zeros((n, 3), dtype=torch.float32, device=dev)}
        for v in tensors.values():
            v.requires_grad_(True)
        deg = config.active_sh_degree(gaussians.sh.shape[1])
        settings = camera_settings(camera, config.background, deg, dev)
        color, radii, (depth, alpha, proj, conic) = self._rasterize(settings, tensors)
        npy = lambda x: x.detach().cpu().numpy()  # noqa: E731
        radii_np = npy(radii).astype(np.int32)
        graph = {"image": color, "alpha": alpha, "depth": depth, "tensors": tensors,
                 "gaussians": gaussians, "opacity_scale": config.opacity_scale,
                 "size": (int(camera.width), int(camera.height))}
        return GswarpRenderOutput(
            image=np.ascontiguousarray(npy(color).transpose(1, 2, 0)), alpha=npy(alpha)[0],
            depth=npy(depth)[0], radii=radii_np,
            means2d=(npy(proj) + np.float32(PIXEL_CENTRE)).astype(np.float32),
            conics=npy(conic), visible=radii_np > 0, graph=graph)

    def render_backward(self, out: GswarpRenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
        """Autograd through gswarp's backward kernels; gradients with respect to activated
        parameters mapped to refgs' raw ones (module docstring)."""
        g = out.graph
        cots = {"image": (v_image, lambda v: np.asarray(v).transpose(2, 0, 1)),
                "alpha": (v_alpha, lambda v: np.asarray(v)[None]),
                "depth": (v_depth, lambda v: np.asarray(v)[None])}
        loss = None
        for name, (v, to_native) in cots.items():
            if v is None:
                continue
            arr = to_native(v)
            if arr.shape != tuple(g[name].shape):
                raise ValueError(f"v_{name}: expected shape {tuple(g[name].shape)} (native), got {arr.shape}")
            term = (g[name] * torch.as_tensor(arr, dtype=torch.float32, device=g[name].device)).sum()
            loss = term if loss is None else loss + term
        ts = g["tensors"]
        inputs = [ts[k] for k in ("means", "scales", "quats", "opacities", "sh", "means2d")]
        grads = torch.autograd.grad(loss, inputs, retain_graph=True, allow_unused=True)
        arr = [np.zeros(tuple(x.shape)) if d is None else d.detach().cpu().numpy().astype(np.float64)
               for x, d in zip(inputs, grads)]
        v_means, v_scales, v_quats, v_opac, v_sh, v_m2d = arr
        v_opac = v_opac.reshape(-1)
        if g["opacity_scale"] is not None:
            v_opac = v_opac * np.asarray(g["opacity_scale"], np.float64)
        W, H = g["size"]
        v_pix = v_m2d[:, :2] / np.array([0.5 * W, 0.5 * H])
        raw = raw_gradients(g["gaussians"].astype("float64"), v_means, v_scales, v_quats, v_opac,
                            v_sh, v_means2d=v_pix, quats_were_unit=True)
        return Gradients(**{f: np.asarray(getattr(raw, f), np.float32) for f in FIELDS + ("means2d",)})


gswarp_float32 = GswarpBackend()
#: pinned to a device: Warp's CPU device (with cooperative CPU blocks), or CUDA
gswarp_cpu = GswarpBackend("cpu")
gswarp_cuda = GswarpBackend("cuda")

__all__ = ["GswarpBackend", "GswarpRenderOutput", "camera_settings", "gswarp_cpu", "gswarp_cuda",
           "gswarp_float32"]
