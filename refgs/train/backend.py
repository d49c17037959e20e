"""The backend seam: the trainer reaches a renderer only through an object chosen by name.

A backend has ``name`` and two methods with the signatures of ``refgs.render`` and
``refgs.render_backward``::

    render(gaussians, camera, config) -> RenderOutput-like (image, radii, means2d, ...)
    render_backward(out, v_image, v_alpha=None, v_depth=None) -> Gradients

and optionally ``ssim_and_grad(img, gt)`` (the signature of ``refgs.metrics.ssim.ssim_and_grad``)
used by the loss in place of the reference's, and ``adam_update(p, g, m, v, lr, keep, step, betas,
eps) -> bool`` used by ``refgs.train.adam.Adam`` for one parameter's update (False: not taken).

"reference" is the numpy specification itself; "fast" is refgs.fast (numba).  Another backend
registers itself with ``register_backend`` and is picked with ``--backend NAME`` without touching
training code (docs/spec/training.md TRN-08).
"""
from __future__ import annotations

from typing import Callable

from ..errors import ConfigError


class ReferenceBackend:
    """refgs.render / refgs.render_backward, unchanged."""

    name = "reference"

    def render(self, gaussians, camera, config):
        from ..render import render
        return render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        from ..render import render_backward
        return render_backward(out, v_image, v_alpha, v_depth)


class FastBackend:
    """refgs.fast (numba; optional extra ``numba``), same API; imported when first chosen."""

    name = "fast"

    def __init__(self):
        try:
            from .. import fast
        except ImportError as e:
            raise ConfigError(f"--backend fast: {e}") from None
        self._fast = fast

    def render(self, gaussians, camera, config):
        return self._fast.render(gaussians, camera, config)

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        return self._fast.render_backward(out, v_image, v_alpha, v_depth)

    def ssim_and_grad(self, img, gt):
        """The loss's SSIM and its gradient, compiled (refgs.fast.ssim; equal to the reference's
        refgs.metrics.ssim.ssim_and_grad to ~1e-15 relative)."""
        from ..fast.ssim import ssim_and_grad
        return ssim_and_grad(img, gt)

    @staticmethod
    def adam_update(p, g, m, v, lr, keep, step, betas, eps) -> bool:
        """Adam's update of one parameter, compiled (refgs.fast.adam; bit-identical to the
        numpy expressions of refgs.train.adam.Adam.step, which it replaces when it returns True)."""
        from ..fast.adam import adam_update
        return adam_update(p, g, m, v, lr, keep, step, betas, eps)


_REGISTRY: dict[str, Callable[[], object]] = {"reference": ReferenceBackend, "fast": FastBackend}


def register_backend(name: str, factory: Callable[[], object]) -> None:
    """Make ``factory()`` available as backend ``name`` (a later registration replaces one)."""
    _REGISTRY[str(name)] = factory


def available_backends() -> list[str]:
    return sorted(_REGISTRY)


def get_backend(name: str):
    """A new backend object for ``name``; ConfigError naming --backend when unknown."""
    if name not in _REGISTRY:
        raise ConfigError(f"--backend: unknown backend {name!r}; available: "
                          f"{', '.join(available_backends())}")
    return _REGISTRY[name]()


__all__ = ["ReferenceBackend", "register_backend", "available_backends", "get_backend"]
