"""An independent PyTorch transcription of the refgs forward model; gradients by autograd.

Written from the model as stated in docs/spec (conventions.md, stages.md, profiles.md), not by
calling refgs' stage functions, so that refgs' hand-derived backward can be checked against
autograd of a second, separately written forward.  Only refgs'
*containers* (Gaussians, Camera, RenderConfig, Gradients) are shared.  Every constant below is
transcribed again here; tests/test_torch_autograd.py checks that they equal refgs.constants.

The discrete decisions (culling, radii, tile lists, skips, the stop rule) are computed from
detached values and then held fixed; everything continuous is a torch expression of the five raw
parameter tensors (leaf tensors with ``requires_grad``).  The alpha cap's gradient follows the
profile (RAS-10, PRF-07): inria passes it through the cap as if unclamped, gsplat gives none
where o*G > cap.

Use:  ``render_torch(g, cam, cfg)`` -> dict of tensors, or the oracle backend objects
``torch_float64``, ``torch_float32``, ``torch_gsplat_float64``, ``torch_gsplat_float32``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

try:
    import torch
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "oracle.adapters.torch_backend needs PyTorch; install the optional extra "
        "(pip install 'refgs[torch]', which pins torch==2.13.0)") from exc

from refgs import Gradients, RenderConfig
from refgs.render import validate_inputs   # input checking only; no stage of the model

# ---------------------------------------------------------------------------------------------
# Constants, transcribed from docs/spec/profiles.md and stages.md
# ---------------------------------------------------------------------------------------------

#: tile edge in pixels (RAS-01; BLOCK_X = 16 in diff-gaussian-rasterization, gsplat tile_size 16)
TILE = 16
#: fragments with alpha below 1/255 are skipped (RAS-04)
ALPHA_SKIP = 1.0 / 255.0
#: transmittance threshold of the stop rule (RAS-05)
T_STOP = 1e-4
#: SH colour offset (CNV-10)
COLOR_OFFSET = 0.5
#: real SH constants (SH-02; diff-gaussian-rasterization auxiliary.h SH_C0..SH_C3)
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@dataclass(frozen=True)
class Rules:
    """Per-profile constants (docs/spec/profiles.md, PRF-01..PRF-08)."""

    near: float              # cull depth
    near_inclusive: bool     # inria culls z <= near, gsplat z < near
    far: float               # gsplat also culls z > far
    symmetric_clamp: bool    # inria: +-1.3 tan(fov/2); gsplat: principal-point-aware limits
    eps2d: float             # dilation of the 2D covariance diagonal
    det_nonpositive: bool    # gsplat culls det <= 0, inria only det == 0
    cap: float               # alpha cap
    stop_inclusive: bool     # gsplat stops at T(1-a) <= 1e-4, inria at < 1e-4
    grad_through_cap: bool   # inria: gradient as if unclamped; gsplat: none above the cap


RULES = {
    "inria": Rules(near=0.2, near_inclusive=True, far=math.inf, symmetric_clamp=True, eps2d=0.3,
                   det_nonpositive=False, cap=0.99, stop_inclusive=False, grad_through_cap=True),
    "gsplat": Rules(near=0.01, near_inclusive=False, far=1e10, symmetric_clamp=False, eps2d=0.3,
                    det_nonpositive=True, cap=0.999, stop_inclusive=True, grad_through_cap=False),
}
#: inria radius: ceil(3 sqrt(lambda_max)) with max(0.1, mid^2 - det) under the root (PRJ-05)
INRIA_SIGMA, INRIA_EIG_FLOOR = 3.0, 0.1
#: inria frustum clamp factor 1.3 tan(fov/2); gsplat margin 0.3 tan(fov/2) (PRJ-03)
INRIA_CLAMP, GSPLAT_MARGIN = 1.3, 0.3
#: gsplat per-axis extent 3.33 sigma, shrunk for faint Gaussians (PRJ-05)
GSPLAT_EXTEND = 3.33

DTYPES = {"float64": torch.float64, "float32": torch.float32}
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _const(x, dtype) -> "torch.Tensor":
    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype)


# ---------------------------------------------------------------------------------------------
# Stages (docs/spec/stages.md COV, PRJ, SH, RAS)
# ---------------------------------------------------------------------------------------------

def covariance(quats, log_scales):
    """Sigma = R(q/|q|) diag(s)^2 R^T, s = exp(log_scales) (COV-01).  (N,4), (N,3) -> (N,3,3)."""
    m = quats.detach().abs().amax(dim=-1, keepdim=True)
    qs = quats / torch.where(m > 0, m, torch.ones_like(m))   # q / max|q_k|: no under/overflow (CNV-05)
    u = qs / torch.sqrt((qs * qs).sum(-1, keepdim=True))
    w, x, y, z = u.unbind(-1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                    -1).reshape(-1, 3, 3)
    M = R * torch.exp(log_scales)[:, None, :]
    return M @ M.transpose(-1, -2)


def sh_colors(means, sh, campos, degree: int):
    """max(sum_k b_k(dir) sh_k + 0.5, 0), dir = normalize(mean - campos) (SH-01..SH-03, CNV-10).

    means (N,3), sh (N,K,3), campos (3,) -> (N,3).  Uses coefficients 0..(degree+1)^2 - 1.
    """
    d = means - campos
    n2 = (d * d).sum(-1, keepdim=True)
    d = d / torch.sqrt(torch.where(n2 > 0, n2, torch.ones_like(n2)))
    x, y, z = d.unbind(-1)
    b = [torch.full_like(x, C0)]
    if degree >= 1:
        b += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
              C2[4] * (xx - yy)]
    if degree >= 3:
        b += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
              C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
              C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    basis = torch.stack(b, -1)                                         # (N, B)
    rgb = (basis[:, :, None] * sh[:, :len(b), :]).sum(1) + COLOR_OFFSET
    return torch.clamp(rgb, min=0.0)                                  # rgb == 0 keeps its gradient


def project(means, cov3d, opac, camera, rules: Rules, antialiased: bool):
    """EWA projection, culling and radii (PRJ-01..PRJ-05, PRJ-08).  Rows of culled Gaussians hold
    finite placeholders (computed with t.z := 1) and are dropped by ``visible``.

    means (N,3), cov3d (N,3,3), opac (N,) activated opacity (times opacity_scale).  Returns a dict
    of tensors means2d (N,2), depths (N,), conics (N,3), cov2d (N,3), comp (N,), and numpy
    radii (N,2) int32, visible (N,) bool, rect (N,4) int64 tile rectangle (x0, x1, y0, y1).
    """
    dt = means.dtype
    W, H = int(camera.width), int(camera.height)
    w2c = _const(camera.world_to_camera, dt)
    Rw, tw = w2c[:3, :3], w2c[:3, 3]
    Kn = np.asarray(camera.K, np.float64)
    fx, fy, cx, cy = (_const(Kn[i], dt) for i in ((0, 0), (1, 1), (0, 2), (1, 2)))
    t = means @ Rw.T + tw
    tz = t[:, 2]
    with torch.no_grad():
        front = (tz > rules.near) if rules.near_inclusive else (tz >= rules.near)
        front &= tz <= rules.far
    tz = torch.where(front, tz, torch.ones_like(tz))
    means2d = torch.stack([fx * t[:, 0] / tz + cx, fy * t[:, 1] / tz + cy], -1)
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    if rules.symmetric_clamp:
        lnx = lpx = INRIA_CLAMP * tan_x
        lny = lpy = INRIA_CLAMP * tan_y
    else:
        lnx, lpx = cx / fx + GSPLAT_MARGIN * tan_x, (W - cx) / fx + GSPLAT_MARGIN * tan_x
        lny, lpy = cy / fy + GSPLAT_MARGIN * tan_y, (H - cy) / fy + GSPLAT_MARGIN * tan_y
    u = torch.clamp(t[:, 0] / tz, min=-lnx, max=lpx)   # gradient 0 strictly outside (PRJ-03)
    v = torch.clamp(t[:, 1] / tz, min=-lny, max=lpy)
    zero = torch.zeros_like(tz)
    J = torch.stack([fx / tz, zero, -fx * u / tz, zero, fy / tz, -fy * v / tz], -1).reshape(-1, 2, 3)
    cov_c = torch.einsum("ij,njk,lk->nil", Rw, cov3d, Rw)
    S = J @ cov_c @ J.transpose(-1, -2)
    a = S[:, 0, 0] + rules.eps2d
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    c = S[:, 1, 1] + rules.eps2d
    det = a * c - b * b
    with torch.no_grad():
        det_ok = (det > 0) if rules.det_nonpositive else (det != 0)
    det = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], -1)
    if antialiased:                                                     # PRJ-08
        ratio = ((a - rules.eps2d) * (c - rules.eps2d) - b * b) / det
        pos = ratio > 0
        comp = torch.where(pos, torch.sqrt(torch.where(pos, ratio, torch.ones_like(ratio))), zero)
    else:
        comp = torch.ones_like(tz)
    o_eff = opac * comp

    # radius, tile rectangle, culling: discrete, from detached float64 numpy values
    ad, cd, dd = (q.detach().cpu().numpy().astype(np.float64) for q in (a, c, det))
    m2 = means2d.detach().cpu().numpy().astype(np.float64)
    visible = (front & det_ok).cpu().numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        if rules.symmetric_clamp:       # inria: eigenvalue radius (PRJ-05)
            mid = 0.5 * (ad + cd)
            lam = mid + np.sqrt(np.maximum(INRIA_EIG_FLOOR, mid * mid - dd))
            rx = ry = np.ceil(INRIA_SIGMA * np.sqrt(lam))
        else:                           # gsplat: opacity-aware per-axis extent, off-screen cull
            o = o_eff.detach().cpu().numpy().astype(np.float64)
            visible &= o >= ALPHA_SKIP
            ext = np.minimum(GSPLAT_EXTEND,
                             np.sqrt(2.0 * np.log(np.maximum(o, ALPHA_SKIP) / ALPHA_SKIP)))
            rx, ry = np.ceil(ext * np.sqrt(ad)), np.ceil(ext * np.sqrt(cd))
            visible &= (rx > 0) | (ry > 0)
            mx, my = m2[:, 0], m2[:, 1]
            visible &= (mx + rx > 0) & (mx - rx < W) & (my + ry > 0) & (my - ry < H)
    rect = tile_rect(m2, rx, ry, W, H, rules.symmetric_clamp)
    visible &= (rect[:, 1] > rect[:, 0]) & (rect[:, 3] > rect[:, 2])
    radii = np.where(visible[:, None], np.stack([rx, ry], -1), 0).astype(np.int32)
    return {"means2d": means2d, "depths": t[:, 2], "conics": conics,
            "cov2d": torch.stack([a, b, c], -1), "comp": comp, "opacities": o_eff,
            "radii": radii, "visible": visible, "rect": rect}


def tile_rect(m2, rx, ry, width: int, height: int, inria: bool) -> np.ndarray:
    """Tiles covered by each Gaussian, (x0, x1, y0, y1) with x1, y1 exclusive (RAS-01, PRF-08).

    inria (getRect): integer-centre coordinates p = means2d - 0.5, trunc((p - r)/16) and
    trunc((p + r + 15)/16); gsplat: floor(m/16 - r/16) and ceil(m/16 + r/16); both clipped to the
    tile grid.  m2 (N,2), rx, ry (N,) float64 numpy -> (N,4) int64.
    """
    gx, gy = -(-width // TILE), -(-height // TILE)
    mx, my = m2[:, 0], m2[:, 1]
    with np.errstate(invalid="ignore"):
        if inria:
            px, py = mx - 0.5, my - 0.5
            rect = [np.trunc((px - rx) / TILE), np.trunc((px + rx + TILE - 1) / TILE),
                    np.trunc((py - ry) / TILE), np.trunc((py + ry + TILE - 1) / TILE)]
        else:
            rect = [np.floor(mx / TILE - rx / TILE), np.ceil(mx / TILE + rx / TILE),
                    np.floor(my / TILE - ry / TILE), np.ceil(my / TILE + ry / TILE)]
    return np.stack([np.clip(np.nan_to_num(r, nan=0.0, posinf=L, neginf=0.0), 0, L)
                     for r, L in zip(rect, (gx, gx, gy, gy))], -1).astype(np.int64)


def composite(means2d, conics, opac, colors, depths, visible, rect, width, height, rules, background):
    """Front-to-back compositing per 16x16 tile (RAS-01..RAS-07, RAS-10).

    Each tile's list: visible Gaussians whose rect covers it, by depth then index.  The skip and
    stop decisions are taken on detached values; the weights a_i T_i are then a torch expression
    (exclusive ``cumprod`` of 1 - a over the blended entries).  Returns image (H,W,3), alpha,
    depth, final_T (H,W) tensors and n_contrib (H,W) int32 numpy.
    """
    dt = means2d.dtype
    H, W = height, width
    ids = np.flatnonzero(visible)
    z = depths.detach().cpu().numpy()
    ids = ids[np.lexsort((ids, z[ids]))]                   # depth, ties by index (RAS-02)
    gx, gy = -(-W // TILE), -(-H // TILE)
    pix_all, C_all, D_all, T_all = [], [], [], []
    n_contrib = np.zeros((H, W), np.int32)
    for ty in range(gy):
        for tx in range(gx):
            r = rect[ids]
            lst = ids[(r[:, 0] <= tx) & (tx < r[:, 1]) & (r[:, 2] <= ty) & (ty < r[:, 3])]
            if lst.size == 0:
                continue
            rows = np.arange(ty * TILE, min(H, ty * TILE + TILE))
            cols = np.arange(tx * TILE, min(W, tx * TILE + TILE))
            rr, cc = (q.ravel() for q in np.meshgrid(rows, cols, indexing="ij"))
            g = torch.as_tensor(lst)
            px = torch.as_tensor(cc + 0.5, dtype=dt)[:, None]          # CNV-08 pixel centres
            py = torch.as_tensor(rr + 0.5, dtype=dt)[:, None]
            dx = means2d[g, 0][None, :] - px
            dy = means2d[g, 1][None, :] - py
            A, B, Cc = conics[g, 0][None], conics[g, 1][None], conics[g, 2][None]
            power = -0.5 * (A * dx * dx + Cc * dy * dy) - B * dx * dy  # RAS-03
            pos_pow = (power > 0).detach()
            G = torch.exp(torch.where(pos_pow, torch.zeros_like(power), power))
            oG = opac[g][None] * G
            over = (oG > rules.cap).detach()
            if rules.grad_through_cap:                                 # RAS-04, RAS-10
                alpha = torch.where(over, rules.cap + (oG - oG.detach()), oG)
            else:
                alpha = torch.where(over, torch.full_like(oG, rules.cap), oG)
            with torch.no_grad():
                valid = ~pos_pow & (alpha >= ALPHA_SKIP)
                incl = torch.cumprod(torch.where(valid, 1 - alpha, torch.ones_like(alpha)), 1)
                stop = valid & ((incl <= T_STOP) if rules.stop_inclusive else (incl < T_STOP))
                before_stop = torch.cumsum(stop.to(torch.int64), 1) == 0   # RAS-05: exclusive
                blended = valid & before_stop
            a_b = torch.where(blended, alpha, torch.zeros_like(alpha))
            Tcum = torch.cumprod(1 - a_b, 1)
            T_before = torch.cat([torch.ones_like(Tcum[:, :1]), Tcum[:, :-1]], 1)
            w = a_b * T_before
            C_all.append(w @ colors[g])
            D_all.append(w @ depths[g])
            T_all.append(Tcum[:, -1])
            pix_all.append(rr * W + cc)
            slot = torch.arange(1, lst.size + 1)[None, :]
            n_contrib[rr, cc] = torch.where(blended, slot, 0).amax(1).numpy()
    C = torch.zeros(H * W, 3, dtype=dt)
    D = torch.zeros(H * W, dtype=dt)
    T = torch.ones(H * W, dtype=dt)
    if pix_all:
        pix = torch.as_tensor(np.concatenate(pix_all))
        C = C.index_copy(0, pix, torch.cat(C_all))
        D = D.index_copy(0, pix, torch.cat(D_all))
        T = T.index_copy(0, pix, torch.cat(T_all))
    bg = _const(background, dt)
    image = (C + T[:, None] * bg).reshape(H, W, 3)                     # RAS-06
    return {"image": image, "alpha": (1 - T).reshape(H, W), "depth": D.reshape(H, W),
            "final_T": T.reshape(H, W), "n_contrib": n_contrib}


def render_torch(gaussians, camera, config: RenderConfig | None = None, dtype: str = "float64",
                 params: dict | None = None) -> dict:
    """The whole forward model in torch (COV-01, PRJ-01..PRJ-08, SH-01..SH-03, RAS-01..RAS-06).

    gaussians: refgs.Gaussians (numpy); camera: refgs.Camera; config: refgs.RenderConfig.
    params: optional dict of the five raw tensors to use instead of fresh leaves made from
    ``gaussians`` (all must have the torch dtype named by ``dtype``).
    Returns a dict of tensors image (H,W,3), alpha, depth, final_T (H,W), means2d (N,2),
    depths (N,), conics (N,3), cov2d (N,3), colors (N,3), opacities (N,), numpy n_contrib (H,W),
    radii (N,2), visible (N,), and ``params`` (the leaf tensors, requires_grad).
    """
    config = RenderConfig() if config is None else config
    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected one of {sorted(DTYPES)}, got {dtype!r}")
    if config.profile not in RULES:
        raise ValueError(f"RenderConfig.profile: expected one of {sorted(RULES)}, "
                         f"got {config.profile!r}")
    rules = RULES[config.profile]
    if config.antialiased and config.profile != "gsplat":
        raise ValueError("RenderConfig.antialiased: expected False unless profile is 'gsplat'")
    td = DTYPES[dtype]
    if params is None:
        params = {f: torch.tensor(np.asarray(getattr(gaussians, f)), dtype=td, requires_grad=True)
                  for f in FIELDS}
    if not bool(torch.all(torch.any(params["quats"] != 0, dim=-1))):
        raise ValueError("Gaussians.quats: expected non-zero quaternions (CNV-05)")
    K = params["sh"].shape[1]
    degree = config.active_sh_degree(K)
    if not 0 <= degree <= 3 or (degree + 1) ** 2 > K:
        raise ValueError(f"RenderConfig.sh_degree: degree {degree} needs 0..3 and "
                         f"K >= {(degree + 1) ** 2}, got K = {K}")
    cov3d = covariance(params["quats"], params["log_scales"])
    opac = torch.sigmoid(params["opacity_logits"])
    if config.opacity_scale is not None:
        opac = opac * _const(config.opacity_scale, td)
    proj = project(params["means"], cov3d, opac, camera, rules, config.antialiased)
    w2c = np.asarray(camera.world_to_camera, np.float64)
    campos = _const(-w2c[:3, :3].T @ w2c[:3, 3], td)
    colors = sh_colors(params["means"], params["sh"], campos, degree)
    comp = composite(proj["means2d"], proj["conics"], proj["opacities"], colors, proj["depths"],
                     proj["visible"], proj["rect"], int(camera.width), int(camera.height), rules,
                     config.background)
    return {**comp, **{k: proj[k] for k in ("means2d", "depths", "conics", "cov2d", "radii",
                                            "visible", "opacities")},
            "colors": colors, "params": params}


# ---------------------------------------------------------------------------------------------
# The oracle backend
# ---------------------------------------------------------------------------------------------

@dataclass
class TorchRenderOutput:
    """Numpy views of a ``render_torch`` result; ``graph`` keeps the tensors for the backward."""

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    n_contrib: np.ndarray
    radii: np.ndarray
    means2d: np.ndarray
    depths: np.ndarray
    conics: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    final_T: np.ndarray
    visible: np.ndarray
    graph: dict = field(repr=False, default_factory=dict)


class TorchBackend:
    """Oracle backend (oracle/protocol.py): forward by :func:`render_torch`, backward by torch
    autograd, and the four stage functions of the transcription."""

    max_sh_degree = 3
    has_backward = True
    supports_opacity_scale = True

    def __init__(self, profile: str = "inria", dtype: str = "float64"):
        if profile not in RULES:
            raise ValueError(f"profile: expected one of {sorted(RULES)}, got {profile!r}")
        if dtype not in DTYPES:
            raise ValueError(f"dtype: expected one of {sorted(DTYPES)}, got {dtype!r}")
        self.profile, self.dtype = profile, dtype
        self.supports_antialiased = profile == "gsplat"
        self.name = f"torch-autograd-{profile}-{dtype}"
        self.version = f"torch {torch.__version__}"

    def _t(self, x):
        return _const(x, DTYPES[self.dtype])

    def render(self, gaussians, camera, config: RenderConfig | None = None) -> TorchRenderOutput:
        config = RenderConfig(profile=self.profile) if config is None else config
        if config.profile != self.profile:
            raise ValueError(f"RenderConfig.profile: this backend renders {self.profile!r}, "
                             f"got {config.profile!r}")
        validate_inputs(gaussians, camera, config)      # input errors as refgs words them (API-03)
        r = render_torch(gaussians, camera, config, self.dtype)
        npy = {k: (v.detach().cpu().numpy() if torch.is_tensor(v) else v) for k, v in r.items()
               if k != "params" and k != "cov2d"}
        return TorchRenderOutput(**npy, graph=r)

    def render_backward(self, out: TorchRenderOutput, v_image, v_alpha=None, v_depth=None) -> Gradients:
        """dL/d(raw parameters) and dL/dmeans2d (pixels) by autograd, for
        L = <v_image, image> + <v_alpha, alpha> + <v_depth, depth> (API-05)."""
        if not isinstance(out, TorchRenderOutput):
            raise ValueError("out: expected the TorchRenderOutput of this backend's render, "
                             f"got {type(out).__name__}")
        g = out.graph
        td = g["image"].dtype
        loss = torch.zeros((), dtype=td)
        for name, v in (("image", v_image), ("alpha", v_alpha), ("depth", v_depth)):
            if v is None:
                continue
            v = np.asarray(v)
            if v.shape != tuple(g[name].shape):
                raise ValueError(f"v_{name}: expected shape {tuple(g[name].shape)}, got {v.shape}")
            loss = loss + (g[name] * torch.as_tensor(v, dtype=td)).sum()
        inputs = [g["params"][f] for f in FIELDS] + [g["means2d"]]
        if not loss.requires_grad:
            grads = [None] * len(inputs)
        else:
            grads = torch.autograd.grad(loss, inputs, retain_graph=True, allow_unused=True)
        arrs = [np.zeros(tuple(x.shape), out.image.dtype) if d is None else d.detach().cpu().numpy()
                for x, d in zip(inputs, grads)]
        return Gradients(*arrs)


    # ---- stage functions (oracle/protocol.py) -----------------------------------------------
    def stage_covariance(self, quats, log_scales) -> np.ndarray:
        return covariance(self._t(quats), self._t(log_scales)).numpy()

    def stage_projection(self, means, cov3d, opacities, camera, config) -> dict:
        p = project(self._t(means), self._t(cov3d), self._t(opacities), camera, RULES[self.profile],
                    bool(config.antialiased))
        return {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in p.items()}

    def stage_sh(self, means, sh, campos, degree) -> np.ndarray:
        return sh_colors(self._t(means), self._t(sh), self._t(campos), int(degree)).numpy()

    def stage_composite(self, means2d, conics, opacities, colors, depths, radii, camera, config) -> dict:
        W, H = int(camera.width), int(camera.height)
        radii = np.asarray(radii)
        rect = tile_rect(np.asarray(means2d, np.float64), radii[:, 0].astype(np.float64),
                         radii[:, 1].astype(np.float64), W, H, RULES[self.profile].symmetric_clamp)
        visible = np.any(radii > 0, axis=-1) & (rect[:, 1] > rect[:, 0]) & (rect[:, 3] > rect[:, 2])
        r = composite(self._t(means2d), self._t(conics), self._t(opacities), self._t(colors),
                      self._t(depths), visible, rect, W, H, RULES[self.profile], config.background)
        return {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in r.items()}


torch_float64 = TorchBackend("inria", "float64")
torch_float32 = TorchBackend("inria", "float32")
torch_gsplat_float64 = TorchBackend("gsplat", "float64")
torch_gsplat_float32 = TorchBackend("gsplat", "float32")

__all__ = ["render_torch", "TorchBackend", "TorchRenderOutput", "covariance", "project",
           "sh_colors", "composite", "RULES", "torch_float64", "torch_float32",
           "torch_gsplat_float64", "torch_gsplat_float32"]
