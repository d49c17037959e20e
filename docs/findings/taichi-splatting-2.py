"""taichi-splatting 0.13.0: ``Gaussians3D.rotation`` is documented as "quaternion wxyz"
(taichi_splatting/data_types.py:42), but every kernel reads it scalar-last, (x, y, z, w):
``quat_to_mat`` unpacks ``x, y, z, w = q`` (taichi_lib/generic.py:342; the torch reference
torch_ops/transforms.py:7 does the same).  A caller who follows the documentation gets a
different rotation.

Scene: one Gaussian with scales (0.1, 0.02, 0.02) at depth 1 in front of a camera with f = 100,
rotated 90 degrees about the viewing axis.  In the documented order that is
q = (w, x, y, z) = (cos 45, 0, 0, sin 45): the long axis turns from image x to image y, so the
2D covariance is about diag(4.3, 100.3) and the conic's first entry about 1 / 4.3.  Read as
(x, y, z, w) the same four numbers are a 90 degree turn about the image x axis, which leaves the
long axis along x: conic[0] is about 1 / 100.3.

Needs: taichi-splatting 0.13.0, taichi 1.7.4, torch, numpy; CPU as in taichi-splatting-1.py.
Run: python docs/findings/taichi-splatting-2.py   (exit status 1 when the defect shows)
"""
import math
import sys
import types

import taichi as ti
import torch

CUDA = torch.cuda.is_available()
if not CUDA:
    sys.modules["taichi_splatting.cuda_lib"] = types.ModuleType("taichi_splatting.cuda_lib")
ti.init(arch=ti.cuda if CUDA else ti.cpu, log_level=ti.WARN)
from taichi_splatting import Gaussians3D, perspective  # noqa: E402


def conic0(rotation) -> float:
    dev = "cuda" if CUDA else "cpu"
    f32 = dict(dtype=torch.float32, device=dev)
    g = Gaussians3D(position=torch.tensor([[0.0, 0.0, 1.0]], **f32),
                    log_scaling=torch.log(torch.tensor([[0.1, 0.02, 0.02]], **f32)),
                    rotation=torch.tensor([rotation], **f32), alpha_logit=torch.zeros((1, 1), **f32),
                    feature=torch.zeros((1, 3), **f32), batch_size=(1,))
    K = torch.tensor([[100.0, 0, 8], [0, 100.0, 8], [0, 0, 1]], **f32)
    cam = perspective.CameraParams(T_image_camera=K, T_camera_world=torch.eye(4, **f32),
                                   near_plane=0.01, far_plane=100.0, image_size=(16, 16))
    g2d, _ = perspective.project_to_image(g, torch.arange(1, device=dev), cam)
    return float(g2d[0, 2])


def main() -> int:
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    documented = conic0([c, 0.0, 0.0, s])        # (w, x, y, z) as data_types.py documents
    scalar_last = conic0([0.0, 0.0, s, c])       # the same rotation written (x, y, z, w)
    expected = 1.0 / (0.02 ** 2 * 100 ** 2 + 0.3)
    print(f"conic[0] for the documented (w, x, y, z) quaternion: {documented:.5f}")
    print(f"conic[0] for the same rotation as (x, y, z, w):      {scalar_last:.5f}")
    print(f"expected for a 90 degree turn about the view axis:   {expected:.5f}")
    bad = abs(documented - expected) > 1e-3 * expected
    print("defect shown: the documented order is not the order the kernels read" if bad else "no defect")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
