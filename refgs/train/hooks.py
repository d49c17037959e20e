"""The method hook protocol: where a training method enters the 3DGS loop (clause TRN-08).

A training method is an object with the hooks of :class:`Method`.  The trainer
(refgs/train/trainer.py, ``Trainer.step``) calls them at fixed points of one iteration t::

    setup(trainer)                                   once, when the trainer is built
    request = before_render(trainer, t, rng)         what to render           (FM-01..FM-04, DG-01)
    out, grads = render + loss + backward of request (the backend; TRN-01)
    grads = after_backward(trainer, t, request, grads)  gradients of theta    (FM-05, FM-11)
    densify and prune -> on_densify(trainer, remap)  rows moved               (TRN-05, FM-08)
    Adam step, leaving frozen_rows(trainer, t) alone (not at t = T)          (TRN-02, FM-08)
    after_step(trainer, t, rng)                      e.g. reinitialisation    (FM-06, FM-07)

``state_arrays`` / ``load_state_arrays`` carry the method's state through checkpoints (TRN-09);
``params_dict`` gives the parameters recorded in config.json (DG-02).

Every hook of the base class is a no-op, so ``Method()`` is plain 3DGS (``--method 3dgs``,
DG-02) and a method overrides only the hooks it needs.  ``rng`` is the run's ``method`` random
stream (TRN-09): a method draws its randomness from it, and only from it, so a seed gives the
same bytes.  What a hook may read and change on ``trainer``:

    trainer.params   name -> parameter array (refgs.Gaussians fields), the stored theta
    trainer.adam     the optimiser; a method changes its state only through its methods
                     (``Adam.zero``, ``Adam.reset_rows``), never by writing ``m`` / ``v``
    trainer.cfg, trainer.extent, trainer.n, trainer.gaussians()
    trainer.loss_and_grads(...) with trainer.current_view / trainer.current_render_config:
                     a second render of the same iteration (FM-11)
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..types import Gaussians


@dataclass
class RenderRequest:
    """What a method asks the backend to render at one iteration.

    gaussians      the Gaussians to render (theta, or a perturbed theta_hat, FM-01..FM-04)
    opacity_scale  None or (N,) per-Gaussian factors on the activated opacity (DG-01)
    extra          anything the method wants back in ``after_backward`` (e.g. the offsets)
    """

    gaussians: Gaussians
    opacity_scale: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


class Method:
    """Plain 3DGS: every hook a no-op (DG-02); the base of every training method (TRN-08)."""

    #: the name recorded in checkpoints (``state_meta``)
    name = "3dgs"

    def setup(self, trainer) -> None:
        """Called once by ``Trainer.__init__`` after the trainer's state exists (e.g. resolve a
        default that depends on the scene extent, FM-01 ``iso_fixed``)."""

    def before_render(self, trainer, t: int, rng: np.random.Generator) -> RenderRequest:
        """What to render at iteration t: the stored Gaussians, unperturbed (TRN-01)."""
        return RenderRequest(trainer.gaussians())

    def after_backward(self, trainer, t: int, request: RenderRequest, grads) -> dict:
        """Gradients Adam applies to the stored parameters, from the backend's ``grads``
        (refgs.Gradients of the rendered ``request``): name -> array shaped like the parameter.
        Plain 3DGS: the gradients themselves (TRN-02)."""
        return grads.params()

    def frozen_rows(self, trainer, t: int) -> dict | None:
        """None, or name -> bool array (N,) or broadcasting against the parameter: rows whose
        values and Adam moments the step at iteration t leaves unchanged (``Adam.step``)."""
        return None

    def on_densify(self, trainer, remap) -> None:
        """Densify-and-prune changed the rows: new row i came from old row ``remap.parent[i]``
        (refgs.train.densify.Remap, TRN-05); per-Gaussian method state follows it."""

    def after_step(self, trainer, t: int, rng: np.random.Generator) -> None:
        """End of iteration t, after densification and the Adam step."""

    def state_arrays(self) -> dict:
        """Method state for a checkpoint: name -> plain array (stored as ``method/<name>``)."""
        return {}

    def load_state_arrays(self, arrays: dict) -> None:
        """Restore what ``state_arrays`` returned (TRN-09)."""

    def params_dict(self) -> dict:
        """Every parameter of the method with its value, as recorded in config.json (DG-02)."""
        return {}


__all__ = ["Method", "RenderRequest"]
