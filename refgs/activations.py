"""Activated parameters and the chain rule back to refgs' raw ones (API-01, API-05; CNV-04..CNV-07).

For a backend that works with activated parameters (scales, opacities, unit quaternions), as most
3DGS renderers do: ``to_activated`` gives its inputs from a ``refgs.Gaussians``, and
``raw_gradients`` turns its gradients back into a ``refgs.Gradients`` the oracle and the trainer
compare and consume.  Used by the oracle's adapters and its backend template
(``oracle/adapters/template.py``).
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit

from .covariance import normalize_quats
from .types import Gaussians, Gradients


def to_activated(gaussians: Gaussians) -> dict[str, np.ndarray]:
    """Activated parameters in the Gaussians' dtype (CNV-04..CNV-07):

    means (N,3); scales (N,3) = exp(log_scales); quats (N,4) unit (w,x,y,z), with refgs' exact
    rescale of tiny quaternions; opacities (N,) = sigmoid(logits); sh (N,K,3) unchanged.
    Raises ValueError on a zero quaternion (CNV-05).
    """
    g = gaussians
    if len(g) and np.any(~np.any(g.quats != 0, axis=-1)):
        row = int(np.flatnonzero(~np.any(g.quats != 0, axis=-1))[0])
        raise ValueError(f"Gaussians.quats: expected non-zero quaternions (CNV-05), row {row} is zero")
    q_unit, _, _ = normalize_quats(g.quats) if len(g) else (g.quats, None, None)
    return {"means": g.means, "scales": np.exp(g.log_scales), "quats": q_unit,
            "opacities": expit(g.opacity_logits), "sh": g.sh}


def raw_gradients(gaussians: Gaussians, v_means, v_scales, v_quats, v_opacities, v_sh,
                  v_means2d=None, quats_were_unit: bool = True) -> Gradients:
    """Map gradients with respect to activated parameters back to refgs' raw ones (API-05).

    v_scales -> v_log_scales = s * v_s (CNV-06); v_opacities -> v_logits = o (1 - o) v_o (CNV-07);
    v_quats: if the backend was given the unit quaternion u (``quats_were_unit``),
    v_q = (I - u u^T) v_u / |q| (CNV-05), else passed through.  Output dtype = the Gaussians'.
    """
    g = gaussians
    dt = g.means.dtype
    s = np.exp(g.log_scales)
    o = expit(g.opacity_logits)
    v_quats = np.asarray(v_quats, dt)
    if quats_were_unit and len(g):
        u, norm, _ = normalize_quats(g.quats)
        v_quats = (v_quats - u * np.sum(u * v_quats, axis=-1, keepdims=True)) / norm[:, None]
    n = len(g)
    m2d = np.zeros((n, 2), dt) if v_means2d is None else np.asarray(v_means2d, dt)
    return Gradients(means=np.asarray(v_means, dt), log_scales=(np.asarray(v_scales, dt) * s).astype(dt),
                           quats=v_quats.astype(dt), opacity_logits=(np.asarray(v_opacities, dt) * o * (1 - o)).astype(dt),
                           sh=np.asarray(v_sh, dt), means2d=m2d)


__all__ = ["to_activated", "raw_gradients"]
