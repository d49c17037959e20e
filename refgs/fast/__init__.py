"""refgs.fast: numba-compiled, parallel forward and backward with the reference's API (issue 7).

    refgs.fast.render(gaussians, camera, config) -> refgs.RenderOutput
    refgs.fast.render_backward(out, v_image, v_alpha=None, v_depth=None) -> refgs.Gradients

The same model as refgs.render (every clause of docs/spec), compiled with numba: per-Gaussian
stages in parallel over Gaussians, compositing in parallel over tiles with each pixel's loop
sequential front to back, a race-free fixed-order gradient reduction (bit-identical results for
any thread count).  Kernels compile once per dtype and are cached on disk.  Oracle backends:
``fast_float32``, ``fast_float64``, ``fast_gsplat_float32``, ``fast_gsplat_float64``.
Design, accuracy and timings: docs/fast.md.

numba is an optional dependency: ``import refgs`` never imports it; importing this package
without it raises ImportError naming ``pip install refgs[numba]``.
"""
try:
    import numba  # noqa: F401
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "refgs.fast needs numba, an optional dependency: pip install 'refgs[numba]'") from exc

from .render import render, render_backward  # noqa: E402
from .backend import (FastBackend, fast_float32, fast_float64, fast_gsplat_float32,  # noqa: E402
                      fast_gsplat_float64)

__all__ = ["render", "render_backward", "FastBackend", "fast_float32", "fast_float64",
           "fast_gsplat_float32", "fast_gsplat_float64"]
