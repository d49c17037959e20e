"""taichi-splatting 0.13.0: in float64 the projection adds the dilation ``blur_cov`` = 0.3
rounded to float32 (0.30000001192...), because the projection kernel declares the argument
``blur_cov: ti.f32`` (taichi_splatting/perspective/projection.py:43).  Every float64 conic then
carries a relative error of up to ~4e-8 -- eight orders above float64 rounding.

Scene: one isotropic Gaussian, scale s = 0.01, at depth z = 1 on the optical axis of a camera
with f = 1: the dilated 2D covariance is s^2 f^2 / z^2 + 0.3 on the diagonal, so the conic's
first entry is exactly 1 / (1e-4 + 0.3).

Needs: taichi-splatting 0.13.0, taichi 1.7.4, torch, numpy.  Runs on the CPU: the projection is
a plain Taichi kernel; only ``import taichi_splatting`` needs a CUDA toolkit (it JIT-compiles
taichi_splatting/cuda_lib at import, cuda_lib/__init__.py:10), so without CUDA the script
registers an empty stand-in for that module first (the projection never calls it).
Run: python docs/findings/taichi-splatting-1.py   (exit status 1 when the defect shows)
"""
import sys
import types

import numpy as np
import taichi as ti
import torch

CUDA = torch.cuda.is_available()
if not CUDA:
    sys.modules["taichi_splatting.cuda_lib"] = types.ModuleType("taichi_splatting.cuda_lib")
ti.init(arch=ti.cuda if CUDA else ti.cpu, default_fp=ti.f64, log_level=ti.WARN)
from taichi_splatting import Gaussians3D, perspective  # noqa: E402

S, Z, BLUR = 0.01, 1.0, 0.3


def main() -> int:
    dev = "cuda" if CUDA else "cpu"
    f64 = dict(dtype=torch.float64, device=dev)
    g = Gaussians3D(position=torch.tensor([[0.0, 0.0, Z]], **f64),
                    log_scaling=torch.full((1, 3), float(np.log(S)), **f64),
                    rotation=torch.tensor([[0.0, 0.0, 0.0, 1.0]], **f64),   # identity (x, y, z, w)
                    alpha_logit=torch.zeros((1, 1), **f64), feature=torch.zeros((1, 3), **f64),
                    batch_size=(1,))
    cam = perspective.CameraParams(T_image_camera=torch.eye(3, **f64), T_camera_world=torch.eye(4, **f64),
                                   near_plane=0.01, far_plane=100.0, image_size=(16, 16), blur_cov=BLUR)
    g2d, _ = perspective.project_to_image(g, torch.arange(1, device=dev), cam)
    got = float(g2d[0, 2])
    exact = 1.0 / (S * S / (Z * Z) + BLUR)
    blur32 = 1.0 / (S * S / (Z * Z) + float(np.float32(BLUR)))
    rel = abs(got - exact) / exact
    print(f"taichi-splatting float64 conic[0]: {got!r}")
    print(f"exact 1/(s^2 + 0.3):               {exact!r}   relative error {rel:.2e}")
    print(f"with 0.3 rounded to float32:       {blur32!r}   relative error "
          f"{abs(got - blur32) / blur32:.2e}")
    print("defect shown" if rel > 1e-12 else "no defect")
    return 1 if rel > 1e-12 else 0


if __name__ == "__main__":
    sys.exit(main())
