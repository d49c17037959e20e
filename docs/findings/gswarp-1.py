"""gswarp 1.1.0: the backward recovers the final transmittance as 1 - alpha, so gradients on
nearly opaque pixels carry a relative error of about eps / T_final (up to ~1e-3 in float32).

Scene: one pixel, two Gaussians centred exactly on it (G = 1), colours given directly
(colors_precomp).  The front Gaussian's alpha is a1 = min(0.99, o1), the back one's a2 = o2; with
L = <v, image>, dL/dcolor_front = a1 * 1 * v and dL/dcolor_back = a2 (1 - a1) v exactly.  The
original rasterizer stores T_final in the forward and reads it in the backward
(cuda_rasterizer/forward.cu ``final_T[pix_id] = T``, backward.cu ``T_final = final_Ts[pix_id]``);
gswarp computes ``T_final = 1.0 - out_alpha_flat[pixel_id]``
(_internal/backends/warp/backward_kernels.py:607) from the float32 sum of a_i T_i, whose
rounding (~6e-8 absolute near 1) becomes a relative error of ~6e-8 / T_final in every T the
backward reconstructs by dividing by (1 - a_i).

Needs: gswarp 1.1.0, torch, numpy.  Uses CUDA when available (public API); otherwise Warp's CPU
device, which needs two workarounds (gswarp's public entry rejects CPU tensors, and its tile
kernels need ``warp.config.enable_cpu_blocks``).
Run: python docs/findings/gswarp-1.py   (exit status 1 when the defect shows)
"""
import sys

import numpy as np
import torch
import warp as wp

wp.config.log_level = wp.LOG_WARNING     # no banner, no module-load lines
import gswarp  # noqa: E402
from gswarp import GaussianRasterizationSettings, GaussianRasterizer  # noqa: E402

CUDA = torch.cuda.is_available()
DEV = "cuda" if CUDA else "cpu"
if not CUDA:
    wp.config.enable_cpu_blocks = True
    from gswarp._internal.frontend import common, standard_autograd
    from gswarp.methods.baseline_3dgs import METHOD


def rasterize(settings, **kw):
    if CUDA:
        color, _, _ = GaussianRasterizer(settings)(**kw)
        return color
    empty = torch.Tensor([])
    out = standard_autograd.rasterize_gaussians(
        common.plan_for(METHOD), kw["means3D"], kw["means2D"], empty, kw["colors_precomp"],
        kw["opacities"], kw["scales"], kw["rotations"], empty, settings)
    return out[0]


def front_colour_gradient(o1: float, o2: float) -> tuple[float, float, float]:
    """(gswarp's dL/dcolor_front, the exact value, T_final) for L = image.sum()."""
    f32 = dict(dtype=torch.float32, device=DEV)
    eye = torch.eye(4, **f32)
    P = torch.zeros(4, 4, **f32)          # 1x1 image, fx = fy = 1, principal point at the centre
    P[0, 0] = P[1, 1] = 2.0
    P[3, 2] = 1.0
    settings = GaussianRasterizationSettings(
        image_height=1, image_width=1, tanfovx=0.5, tanfovy=0.5, bg=torch.zeros(3, **f32),
        scale_modifier=1.0, viewmatrix=eye, projmatrix=P.T.contiguous(), sh_degree=0,
        campos=torch.zeros(3, **f32), prefiltered=False, auto_tune_verbose=False)
    colors = torch.full((2, 3), 0.5, **f32).requires_grad_(True)
    color = rasterize(
        settings, means3D=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], **f32),
        means2D=torch.zeros(2, 3, **f32, requires_grad=True),
        opacities=torch.tensor([[o1], [o2]], **f32), colors_precomp=colors,
        scales=torch.full((2, 3), 0.1, **f32), rotations=torch.tensor([[1.0, 0, 0, 0]] * 2, **f32))
    color.sum().backward()
    a1 = min(0.99, float(np.float32(o1)))
    a2 = float(np.float32(o2))
    return float(colors.grad[0, 0]), a1, (1 - a1) * (1 - a2)


def main() -> int:
    print(f"gswarp {gswarp.__version__} on {DEV}")
    print(f"{'o2':>8} {'T_final':>10} {'dL/dc_front':>12} {'exact':>8} {'rel. error':>10} "
          f"{'eps/T_final':>11}")
    worst = 0.0
    for o2 in (0.5, 0.9, 0.98, 0.985, 0.989):
        got, exact, t_final = front_colour_gradient(1.0, o2)
        rel = abs(got - exact) / exact
        worst = max(worst, rel)
        print(f"{o2:8.3f} {t_final:10.2e} {got:12.8f} {exact:8.4f} {rel:10.2e} "
              f"{np.finfo(np.float32).eps / t_final:11.2e}")
    # a float32 implementation that keeps T_final is within a few ulps (~1e-7) of the exact value
    print("defect shown" if worst > 1e-5 else "no defect")
    return 1 if worst > 1e-5 else 0


if __name__ == "__main__":
    sys.exit(main())
