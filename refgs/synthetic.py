"""Seeded synthetic scenes (the benchmark scene of docs/performance.md, "How it is measured").

``benchmark_scene(n, width, height, seed)``: N Gaussians with means uniform in the view frustum at
depth 2..8, log-scales uniform in [-5, -3], opacities uniform in [0.05, 0.9], uniformly random
rotations and SH degree 3 coefficients, seen by a camera at the origin looking down +z.
"""
from __future__ import annotations

import numpy as np
from scipy.special import logit

from .types import Camera, Gaussians

#: benchmark scene parameters (docs/performance.md, "How it is measured": Scenes); our choice
DEPTH_RANGE = (2.0, 8.0)
LOG_SCALE_RANGE = (-5.0, -3.0)
OPACITY_RANGE = (0.05, 0.9)
#: focal length as a fraction of the image width (a ~53 degree horizontal field of view)
FOCAL_PER_WIDTH = 1.0
#: spread of the SH coefficients: DC around mid-grey, higher bands small
SH_DC_STD = 0.5
SH_REST_STD = 0.1


def benchmark_camera(width: int, height: int) -> Camera:
    f = FOCAL_PER_WIDTH * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return Camera(np.eye(4), K, int(width), int(height))


def benchmark_scene(n: int, width: int = 504, height: int = 378, seed: int = 0,
                    dtype=np.float64) -> tuple[Gaussians, Camera]:
    """The seeded benchmark scene: (Gaussians, Camera)."""
    rng = np.random.default_rng(seed)
    cam = benchmark_camera(width, height)
    z = rng.uniform(*DEPTH_RANGE, n)
    # uniform in the frustum: image coordinates uniform over the image, then back-projected
    u = rng.uniform(0, width, n)
    v = rng.uniform(0, height, n)
    x = (u - cam.cx) / cam.fx * z
    y = (v - cam.cy) / cam.fy * z
    means = np.stack([x, y, z], -1)
    log_scales = rng.uniform(*LOG_SCALE_RANGE, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    opac = logit(rng.uniform(*OPACITY_RANGE, n))
    sh = rng.normal(0, SH_REST_STD, (n, 16, 3))
    sh[:, 0, :] = rng.normal(0, SH_DC_STD, (n, 3))
    g = Gaussians(means, log_scales, q, opac, sh).astype(dtype)
    return g, cam
