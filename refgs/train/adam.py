"""Adam over named parameter arrays whose rows are Gaussians (clause TRN-02).

The update is torch.optim.Adam's (single-tensor path, amsgrad off, weight decay 0), which is what
3DGS uses (graphdeco-inria/gaussian-splatting@82bc469 ``training_setup``; peers.md 1.6)::

    m <- m + (1 - b1) (g - m)            (torch ``exp_avg.lerp_(grad, 1 - beta1)``)
    v <- b2 v + (1 - b2) g^2
    p <- p - lr / (1 - b1^s) * m / (sqrt(v) / sqrt(1 - b2^s) + eps)

with ``s`` the step count of that parameter.  As in torch, every parameter has its own step
count, and a parameter left out of a step (3DGS: every parameter on a densification iteration,
the opacity on an opacity-reset iteration, because the tensor was replaced and has no gradient)
neither moves nor counts the step.

Rows are Gaussians: densification changes N and the moments follow their rows
(``remap``: rows copied from an old row keep its moments, new rows start at zero, as 3DGS
``cat_tensors_to_optimizer`` / ``_prune_optimizer``); ``zero`` clears the moments of a parameter
(3DGS ``replace_tensor_to_optimizer`` at the opacity reset) and ``reset_rows`` those of some rows
(the flat-minima reinitialisation, docs/spec/method.md FM-07/FM-08): a training method changes
the optimiser's state only through these.  The learning rate may be an array
broadcasting against the parameter: refgs stores all SH coefficients in one (N, K, 3) array and
gives the DC slice and the rest their own rates with an lr of shape (1, K, 1).
"""
from __future__ import annotations

import numpy as np

#: Adam's epsilon in 3DGS (``torch.optim.Adam(l, lr=0.0, eps=1e-15)``).  [TRN-02]
ADAM_EPS = 1e-15
#: torch.optim.Adam default betas (3DGS passes none).  [TRN-02]
ADAM_BETAS = (0.9, 0.999)


class Adam:
    """Adam state for named arrays (TRN-02).

    m, v   dict name -> array shaped like the parameter (same dtype)
    steps  dict name -> int, the parameter's step count
    """

    def __init__(self, params: dict, betas=ADAM_BETAS, eps: float = ADAM_EPS, kernel=None):
        #: optional compiled update (refgs.fast.adam.adam_update: the same arithmetic in one
        #: pass, bit-identical); it returns False for shapes it does not take
        self.kernel = kernel
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.m = {k: np.zeros_like(p) for k, p in params.items()}
        self.v = {k: np.zeros_like(p) for k, p in params.items()}
        self.steps = {k: 0 for k in params}

    def step(self, params: dict, grads: dict, lrs: dict, skip=(), frozen_rows: dict | None = None):
        """Update ``params`` in place.

        grads        name -> gradient shaped like the parameter
        lrs          name -> learning rate (float or array broadcasting against the parameter)
        skip         names not stepped this time (no move, step count unchanged)
        frozen_rows  optional name -> (N,) bool: rows that keep parameter and moments unchanged
                     (the step count still advances; a hook for methods that freeze Gaussians),
                     or a bool array broadcasting against the parameter (e.g. (N, K, 1) to
                     freeze some SH coefficients of some rows)
        """
        b1, b2 = self.betas
        for name, p in params.items():
            if name in skip:
                continue
            g = np.asarray(grads[name], dtype=p.dtype)
            if g.shape != p.shape:
                raise ValueError(f"Adam.step: gradient of {name} has shape {g.shape}, "
                                 f"parameter {p.shape}")
            m, v = self.m[name], self.v[name]
            s = self.steps[name] + 1
            self.steps[name] = s
            keep = None if frozen_rows is None else frozen_rows.get(name)
            if self.kernel is not None and self.kernel(p, g, m, v, lrs[name], keep, s,
                                                       self.betas, self.eps):
                continue
            m_new = m + (1.0 - b1) * (g - m)
            v_new = b2 * v + (1.0 - b2) * g * g
            step_size = np.asarray(lrs[name], dtype=np.float64) / (1.0 - b1 ** s)
            denom = np.sqrt(v_new) / np.sqrt(1.0 - b2 ** s) + self.eps
            p_new = p - (step_size * (m_new / denom)).astype(p.dtype)
            if keep is not None:
                keep = np.asarray(keep, bool)
                if keep.ndim == 1:
                    keep = keep.reshape((-1,) + (1,) * (p.ndim - 1))
                m_new = np.where(keep, m, m_new)
                v_new = np.where(keep, v, v_new)
                p_new = np.where(keep, p, p_new)
            m[...] = m_new
            v[...] = v_new
            p[...] = p_new

    def remap(self, source: np.ndarray) -> None:
        """Rows after densification: new row i takes old row ``source[i]``'s moments, or zeros
        where ``source[i] < 0`` (TRN-05)."""
        source = np.asarray(source, np.int64)
        take = np.maximum(source, 0)
        fresh = source < 0
        for name in self.m:
            for store in (self.m, self.v):
                a = store[name][take]
                a[fresh] = 0
                store[name] = a

    def zero(self, name: str) -> None:
        """Clear the moments of ``name`` (step count kept, as replace_tensor_to_optimizer)."""
        self.m[name][...] = 0
        self.v[name][...] = 0

    def reset_rows(self, name: str, rows) -> None:
        """Clear the moments of some rows of ``name``; its step count is kept (one count per
        tensor, as in torch), so the next step of those rows is bias-corrected for it (FM-08).

        rows  (N,) bool or integer row indices; or a bool array broadcasting against the
              parameter (e.g. (N, K, 1) for some SH coefficients of some rows), the convention
              of ``step``'s ``frozen_rows``
        """
        rows = np.asarray(rows)
        shape = self.m[name].shape
        if rows.dtype == bool and rows.shape != shape[:1]:
            try:
                rows = np.broadcast_to(rows, shape)
            except ValueError:
                raise ValueError(f"Adam.reset_rows: mask of shape {rows.shape} does not broadcast "
                                 f"against {name} {shape}") from None
        elif rows.dtype != bool and not np.issubdtype(rows.dtype, np.integer):
            raise ValueError(f"Adam.reset_rows: rows of {name} must be bool or integer indices, "
                             f"got {rows.dtype}")
        for store in (self.m, self.v):
            store[name][rows] = 0

    # --- checkpoint (plain arrays, no pickles) ------------------------------------------------
    def state_arrays(self) -> dict:
        out = {}
        for name in self.m:
            out[f"adam/m/{name}"] = self.m[name]
            out[f"adam/v/{name}"] = self.v[name]
            out[f"adam/step/{name}"] = np.int64(self.steps[name])
        return out

    def load_state_arrays(self, arrays: dict) -> None:
        for name in list(self.m):
            self.m[name] = np.array(arrays[f"adam/m/{name}"])
            self.v[name] = np.array(arrays[f"adam/v/{name}"])
            self.steps[name] = int(arrays[f"adam/step/{name}"])


__all__ = ["Adam", "ADAM_EPS", "ADAM_BETAS"]
