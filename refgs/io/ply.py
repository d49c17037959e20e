"""Gaussians as PLY in the standard 3DGS layout (clause TRN-10, docs/spec/training.md).

Layout written by graphdeco-inria/gaussian-splatting@82bc469 ``GaussianModel.save_ply`` /
``construct_list_of_attributes`` and read by every 3DGS viewer: one ``vertex`` element, one
little-endian float32 property per value, in this order::

    x, y, z                 means
    nx, ny, nz              zeros (unused normals)
    f_dc_0 .. f_dc_2        sh[:, 0, c]                  (DC coefficient of channel c)
    f_rest_0 .. f_rest_M-1  M = 3 (K - 1); f_rest_{c (K-1) + (k-1)} = sh[:, k, c]
                            ("channel-major": the original stores features_rest as (N, K-1, 3)
                            and writes ``transpose(1, 2).flatten(1)``)
    opacity                 opacity logit (before the sigmoid)
    scale_0 .. scale_2      log scales
    rot_0 .. rot_3          quaternion w, x, y, z (not normalised)

refgs keeps ``sh`` as one (N, K, 3) array; this module does the slicing both ways.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..types import Gaussians
from .atomic import atomic_path

#: Property type of the standard layout ("f4": float32, as ``save_ply``'s ``dtype_full``).
PLY_FLOAT = "f4"
#: Property types the reader accepts.
PLY_READ_TYPES = ("f4", "f8")


def gaussian_ply_properties(k: int) -> list[str]:
    """Property names, in file order, for K SH coefficients per channel (TRN-10)."""
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{c}" for c in range(3)]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    return names


def gaussians_to_rows(g: Gaussians, float_type: str = PLY_FLOAT) -> np.ndarray:
    """Gaussians -> structured array of the 3DGS vertex layout (TRN-10)."""
    n = len(g.means)
    k = g.sh.shape[1] if g.sh.ndim == 3 else 0
    shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,),
              "sh": (n, k, 3)}
    for name, shape in shapes.items():
        if getattr(g, name).shape != shape or k < 1:
            raise ValueError(f"write_gaussians_ply: Gaussians.{name} has shape "
                             f"{getattr(g, name).shape}, expected {shape} (N = {n}, K >= 1)")
    rows = np.empty(n, dtype=[(name, float_type) for name in gaussian_ply_properties(k)])
    for i, c in enumerate("xyz"):
        rows[c] = g.means[:, i]
        rows["n" + c] = 0.0
    for c in range(3):
        rows[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(1, k):
            rows[f"f_rest_{c * (k - 1) + (j - 1)}"] = g.sh[:, j, c]
    rows["opacity"] = g.opacity_logits
    for i in range(3):
        rows[f"scale_{i}"] = g.log_scales[:, i]
    for i in range(4):
        rows[f"rot_{i}"] = g.quats[:, i]
    return rows


def write_gaussians_ply(path: str | Path, g: Gaussians, float_type: str = PLY_FLOAT) -> Path:
    """Write ``g`` as a binary little-endian PLY in the 3DGS layout, atomically (TRN-10).
    float_type "f4" (standard; float64 values are rounded) or "f8"."""
    from plyfile import PlyData, PlyElement

    if float_type not in PLY_READ_TYPES:
        raise ValueError(f"write_gaussians_ply: float_type must be one of {PLY_READ_TYPES}")
    rows = gaussians_to_rows(g, float_type)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            PlyData([PlyElement.describe(rows, "vertex")], byte_order="<").write(fh)
    return Path(path)


def _indexed(names, prefix: str) -> list[str]:
    pat = re.compile(re.escape(prefix) + r"(\d+)$")
    found = sorted((int(m.group(1)), n) for n in names if (m := pat.match(n)))
    return [n for _, n in found]


def read_gaussians_ply(path: str | Path, dtype=np.float64) -> Gaussians:
    """Read a 3DGS-layout PLY into Gaussians of ``dtype`` (TRN-10); SceneError naming the file
    when it is missing, unreadable, truncated or not in the layout."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: Gaussian PLY file not found")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
    except KeyError:
        raise SceneError(f"{path}: no 'vertex' element (expected the 3DGS Gaussian layout)") from None
    except Exception as exc:
        raise SceneError(f"{path}: not a readable PLY file ({type(exc).__name__}: {exc})") from None
    names = list(v.dtype.names or ())
    rest = _indexed(names, "f_rest_")
    k = len(rest) // 3 + 1
    need = gaussian_ply_properties(k)
    missing = [n for n in need if n not in names]
    if missing or len(rest) % 3 or int(round(np.sqrt(k))) ** 2 != k:
        raise SceneError(f"{path}: not the 3DGS Gaussian layout (missing {missing[:6]}, "
                         f"{len(rest)} f_rest_* properties; expected 3 ((d+1)^2 - 1) for SH degree d)")
    col = lambda n: np.asarray(v[n], dtype=np.float64)  # noqa: E731
    n = len(v)
    sh = np.zeros((n, k, 3))
    for c in range(3):
        sh[:, 0, c] = col(f"f_dc_{c}")
        for j in range(1, k):
            sh[:, j, c] = col(f"f_rest_{c * (k - 1) + (j - 1)}")
    g = Gaussians(np.stack([col(c) for c in "xyz"], 1),
                  np.stack([col(f"scale_{i}") for i in range(3)], 1).reshape(n, 3),
                  np.stack([col(f"rot_{i}") for i in range(4)], 1).reshape(n, 4),
                  col("opacity"), sh)
    for name in Gaussians.FIELDS:
        if not np.all(np.isfinite(getattr(g, name))):
            raise SceneError(f"{path}: non-finite values in {name}")
    return g.astype(dtype)


__all__ = ["write_gaussians_ply", "read_gaussians_ply", "gaussians_to_rows",
           "gaussian_ply_properties", "PLY_FLOAT"]
