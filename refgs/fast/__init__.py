"""refgs.fast: numba-compiled, parallel forward and backward with the reference's API (docs/fast.md).

    refgs.fast.render(gaussians, camera, config) -> refgs.RenderOutput
    refgs.fast.render_backward(out, v_image, v_alpha=None, v_depth=None) -> refgs.Gradients

The same model as refgs.render (every clause of docs/spec), compiled with numba: per-Gaussian
stages in parallel over Gaussians, compositing in parallel over tiles with each pixel's loop
sequential front to back, a race-free fixed-order gradient reduction (bit-identical results for
any thread count).  Kernels compile once per dtype and are cached on disk, and compiled again
when any source file of this package changes (refgs.fast.cache).  Oracle backends:
``fast_float32``, ``fast_float64``, ``fast_gsplat_float32``, ``fast_gsplat_float64`` and the mixed
precision ``fast_float32_geom64``.
Design, accuracy and timings: docs/fast.md.

numba is an optional dependency: ``import refgs`` never imports it; importing this package
without it raises ImportError naming ``pip install refgs[numba]``.
"""
try:
    import numba  # noqa: F401
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "refgs.fast needs numba, an optional dependency: pip install 'refgs[numba]'") from exc

from pathlib import Path as _Path  # noqa: E402

from . import kernels as _kernels  # noqa: E402
from .cache import cache_dir_of as _cache_dir_of, ensure_fresh_cache as _ensure_fresh_cache  # noqa: E402

# numba checks a cached kernel only against its own file: recompile all when any source changed
_ensure_fresh_cache(_Path(__file__).parent, _cache_dir_of(_kernels.composite_forward))

from .render import render, render_backward  # noqa: E402
from .backend import (FastBackend, fast_float32, fast_float32_geom64, fast_float64,  # noqa: E402
                      fast_gsplat_float32, fast_gsplat_float64)

__all__ = ["render", "render_backward", "FastBackend", "fast_float32", "fast_float64",
           "fast_gsplat_float32", "fast_gsplat_float64", "fast_float32_geom64"]
