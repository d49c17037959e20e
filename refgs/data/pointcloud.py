"""PLY point clouds with colours (plyfile): read for initialisation, write atomically (DAT-12).

Layout as 3DGS ``storePly`` / ``fetchPly`` (scene/dataset_readers.py): a ``vertex`` element with
float ``x, y, z`` and ``red, green, blue``; uint8 colours are divided by 255, float colours are
taken to be in [0, 1] already.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..io.atomic import atomic_path


def read_ply(path: str | Path, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(points (P, 3), colors (P, 3) in [0, 1])`` from a PLY file; SceneError naming the
    file when it is missing, unreadable, or lacks x/y/z or red/green/blue."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: point cloud file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:
        raise SceneError(f"{path}: not a readable PLY file ({exc})") from None
    if "vertex" not in ply:
        raise SceneError(f"{path}: no 'vertex' element (expected x, y, z, red, green, blue)")
    v = ply["vertex"].data
    have = set(v.dtype.names or ())
    missing = [c for c in ("x", "y", "z", "red", "green", "blue") if c not in have]
    if missing:
        raise SceneError(f"{path}: vertex element lacks {', '.join(missing)} "
                         "(expected x, y, z, red, green, blue)")
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    raw = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    colors = raw / 255.0 if np.issubdtype(raw.dtype, np.integer) else raw.astype(np.float64)
    if not np.all(np.isfinite(points)):
        raise SceneError(f"{path}: non-finite point coordinates")
    in_range = colors.min(initial=0) >= 0 and colors.max(initial=0) <= 1
    if not (np.all(np.isfinite(colors)) and in_range):
        raise SceneError(f"{path}: colours outside [0, 1] (expected uint8 or floats in [0, 1])")
    return points.astype(dtype), colors.astype(dtype)


def write_ply(path: str | Path, points, colors) -> Path:
    """Write ``points`` (P, 3) (float64) and ``colors`` (P, 3) in [0, 1] (uint8, rounded) as a
    binary PLY, atomically (refgs.io.atomic)."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rgb = np.clip(np.rint(np.asarray(colors, dtype=np.float64).reshape(-1, 3) * 255), 0, 255)
    rows = np.empty(len(pts), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        rows[c] = pts[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        rows[c] = rgb[:, i]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            PlyData([PlyElement.describe(rows, "vertex")]).write(fh)
    return path


__all__ = ["read_ply", "write_ply"]
