"""refgs itself as oracle backends: float64 (the reference, as a backend) and float32.

    refgs_float64, refgs_float32                  inria profile
    refgs_gsplat_float64, refgs_gsplat_float32    gsplat profile (antialiasing supported)

Each is refgs.backends.ReferenceBackend (the registry's ``reference``, ``ref64`` and ``ref32``)
at a fixed profile and dtype.  The float32 backends convert the Gaussians to float32 and run
refgs, which then computes every intermediate in float32 (CNV-11): a model of a float32 GPU
backend with its rounding.  All four expose refgs' stage functions, so the oracle's per-stage
checks run too.
"""
from __future__ import annotations

from refgs.backends import ReferenceBackend


class RefgsBackend(ReferenceBackend):
    """refgs.render / render_backward at a fixed profile and dtype (ORC-01)."""

    def __init__(self, profile: str = "inria", dtype: str = "float64"):
        if profile is None or dtype is None:
            raise ValueError(f"RefgsBackend: expected a fixed profile and dtype, got "
                             f"{profile!r}, {dtype!r}")
        super().__init__(profile, dtype)


refgs_float64 = RefgsBackend("inria", "float64")
refgs_float32 = RefgsBackend("inria", "float32")
refgs_gsplat_float64 = RefgsBackend("gsplat", "float64")
refgs_gsplat_float32 = RefgsBackend("gsplat", "float32")

__all__ = ["RefgsBackend", "refgs_float64", "refgs_float32", "refgs_gsplat_float64",
           "refgs_gsplat_float32"]
