"""The public containers of the spec: Gaussians, Camera, RenderConfig, RenderOutput, Gradients.

Containers do not validate; ``refgs.render`` does (clause API-03).  Shapes use N Gaussians,
K SH coefficients per channel, an image of H rows and W columns.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from .constants import SH_MAX_DEGREE


def _keep_float(x: Any) -> np.ndarray:
    """float32/float64 arrays are kept as given; anything else becomes float64 (API-01)."""
    a = np.asarray(x)
    if a.dtype in (np.float32, np.float64):
        return a
    return np.asarray(a, dtype=np.float64)


@dataclass(frozen=True, init=False)
class Gaussians:
    """Raw (pre-activation) parameters of N Gaussians (clause API-01, CNV-04..CNV-07).

    means          (N, 3)  world positions
    log_scales     (N, 3)  log of the per-axis standard deviations (activation exp, CNV-06)
    quats          (N, 4)  rotation quaternion (w, x, y, z), any non-zero norm (CNV-05)
    opacity_logits (N,)    opacity before the sigmoid (CNV-07)
    sh             (N, K, 3) SH coefficients, K >= (degree + 1)**2, channel last (SH-01)

    A plain container: it does not validate (``render`` does).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __init__(self, means, log_scales, quats, opacity_logits, sh):
        object.__setattr__(self, "means", _keep_float(means))
        object.__setattr__(self, "log_scales", _keep_float(log_scales))
        object.__setattr__(self, "quats", _keep_float(quats))
        object.__setattr__(self, "opacity_logits", _keep_float(opacity_logits))
        object.__setattr__(self, "sh", _keep_float(sh))

    FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")

    def __len__(self) -> int:
        return int(np.shape(self.means)[0]) if np.ndim(self.means) >= 1 else 0

    @property
    def dtype(self) -> np.dtype:
        return self.means.dtype

    def astype(self, dtype) -> "Gaussians":
        return Gaussians(*(getattr(self, f).astype(dtype) for f in self.FIELDS))

    def subset(self, index) -> "Gaussians":
        """Rows ``index`` (bool mask or integer array) of every field."""
        return Gaussians(*(getattr(self, f)[index] for f in self.FIELDS))

    def replace(self, **changes) -> "Gaussians":
        kw = {f: getattr(self, f) for f in self.FIELDS}
        kw.update(changes)
        return Gaussians(**kw)

    def to_dict(self) -> dict[str, np.ndarray]:
        return {f: getattr(self, f) for f in self.FIELDS}

    @staticmethod
    def empty(k: int = 16, dtype=np.float64) -> "Gaussians":
        return Gaussians(np.zeros((0, 3), dtype), np.zeros((0, 3), dtype), np.zeros((0, 4), dtype),
                         np.zeros((0,), dtype), np.zeros((0, k, 3), dtype))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera (clauses CNV-01..CNV-03).

    world_to_camera (4, 4) rigid matrix: x_cam = R x_world + t, camera frame OpenCV
                    (x right, y down, z forward).
    K               (3, 3) intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; read when used.
    width, height   image size in pixels.
    """

    world_to_camera: np.ndarray
    K: np.ndarray
    width: int
    height: int

    @property
    def fx(self) -> float:
        return float(np.asarray(self.K)[0, 0])

    @property
    def fy(self) -> float:
        return float(np.asarray(self.K)[1, 1])

    @property
    def cx(self) -> float:
        return float(np.asarray(self.K)[0, 2])

    @property
    def cy(self) -> float:
        return float(np.asarray(self.K)[1, 2])

    @property
    def rotation(self) -> np.ndarray:
        return np.asarray(self.world_to_camera, dtype=np.float64)[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return np.asarray(self.world_to_camera, dtype=np.float64)[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -R^T t (3,)."""
        return -self.rotation.T @ self.translation

    @staticmethod
    def look_at(eye, target, up=(0.0, -1.0, 0.0), fx=100.0, fy=None, width=64, height=48,
                cx=None, cy=None) -> "Camera":
        """A camera at ``eye`` looking at ``target`` (OpenCV frame: y is down, so the default
        ``up`` hint is world -y)."""
        eye = np.asarray(eye, float)
        z = np.asarray(target, float) - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, -np.asarray(up, float))
        if np.linalg.norm(x) < 1e-12:
            x = np.cross(z, [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        fy = fx if fy is None else fy
        cx = width / 2 if cx is None else cx
        cy = height / 2 if cy is None else cy
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        return Camera(w2c, K, int(width), int(height))


@dataclass(frozen=True)
class RenderConfig:
    """How to render (clause API-02).

    profile     "inria" (default; the original 3DGS rasterizer) or "gsplat" (gsplat 1.5.3).
    sh_degree   active SH degree 0..3; None (default) = the largest the Gaussians carry
                (floor(sqrt(K)) - 1, at most 3).
    background  (3,) colour added with the final transmittance; default black.
    antialiased gsplat's opacity compensation sqrt(det(S)/det(S + eps2d I)) (gsplat profile
                only; default off).
    opacity_scale optional (N,) factor multiplying activated opacities before the alpha cap
                (DropGaussian's training-time compensation; None = 1).
    deviations  names of deviations from the profile to switch on (refgs/deviations.py,
                docs/spec/deviations.md); default none: the reference.
    """

    profile: str = "inria"
    sh_degree: int | None = None
    background: tuple = (0.0, 0.0, 0.0)
    antialiased: bool = False
    opacity_scale: Any = None
    deviations: frozenset = frozenset()

    def active_sh_degree(self, k: int) -> int:
        if self.sh_degree is not None:
            return int(self.sh_degree)
        return int(min(SH_MAX_DEGREE, max(0, int(np.floor(np.sqrt(max(k, 1)))) - 1)))


@dataclass(frozen=True)
class RenderOutput:
    """Result of ``refgs.render`` (clause API-04).  Everything the backward needs is here.

    image     (H, W, 3)  sum_i c_i a_i T_i + T_final * background
    alpha     (H, W)     1 - T_final
    depth     (H, W)     sum_i a_i T_i z_i (unnormalised; depth / alpha is the expected depth)
    n_contrib (H, W) int 1-based position, in the pixel's tile list, of the last blended Gaussian
    radii     (N, 2) int screen radius in pixels per axis (0 = culled; equal columns for inria)
    means2d   (N, 2)     continuous image coordinates (CNV-08)
    depths    (N,)       camera-space z
    conics    (N, 3)     (A, B, C) of the inverse dilated 2D covariance
    cov2d     (N, 3)     (a, b, c) of the dilated 2D covariance
    colors    (N, 3)     clamped SH colours
    opacities (N,)       activated opacity actually used (after compensation / opacity_scale)
    final_T   (H, W)     transmittance after the last blended Gaussian
    """

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    n_contrib: np.ndarray
    radii: np.ndarray
    means2d: np.ndarray
    depths: np.ndarray
    conics: np.ndarray
    cov2d: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    final_T: np.ndarray
    visible: np.ndarray
    gaussians: Gaussians
    camera: Camera
    config: RenderConfig
    # intermediate state kept for the backward (see render.py)
    cache: dict = field(repr=False, compare=False, default_factory=dict)

    @property
    def dtype(self) -> np.dtype:
        return self.image.dtype


@dataclass(frozen=True)
class Gradients:
    """dL/d(raw parameter) for every Gaussians field, plus the screen-space gradient (API-05).

    means (N,3), log_scales (N,3), quats (N,4), opacity_logits (N,), sh (N,K,3) and
    means2d (N,2) = dL/d(2D mean) in pixels (what densification accumulates).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    means2d: np.ndarray

    PARAM_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")

    def to_dict(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def params(self) -> dict[str, np.ndarray]:
        return {f: getattr(self, f) for f in self.PARAM_FIELDS}
