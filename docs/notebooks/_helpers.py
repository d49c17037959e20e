"""Drawing and checking helpers for the teaching notebooks of this folder.

The notebooks import it as ``_helpers``: Jupyter starts their kernel in this folder, and
``python docs/notebooks/NN_name.py`` puts the script's folder first on ``sys.path``; from anywhere
else put this folder on ``PYTHONPATH`` (tests/test_notebooks.py does).  It is not part of the
``refgs`` package.

Nothing here is part of the spec: the notebooks call the spec's own functions (``refgs.render``,
the stage functions, ``refgs.methods``, ``oracle``) and use these helpers only to draw, to
tabulate, and to take finite differences.  Core dependencies only (numpy, matplotlib).

    fd_gradient(f, x)                 Richardson-extrapolated central differences of a scalar f
    relative_error(analytic, numeric) max |a - n| / max |n|, the notebooks' error measure
    ellipse_axes(cov) / add_ellipse   the n-sigma ellipse of a 2x2 covariance
    draw_tiles(ax, w, h, rect)        the 16 x 16 tile grid, covered tiles shaded (RAS-01)
    clamp_bound(ax, mode, s)          the region each FM-04 clamp reading allows, x-y projection
    text_table(rows, headers)         a fixed-width table for printing
    show_image(ax, img, title)        imshow without ticks, clipped to [0, 1]
    tiny_demo_views(...)              3 training views of the demo scene at 40 x 30 pixels, the
                                      points triangulated from those views, initial Gaussians
"""
from __future__ import annotations

import tempfile

import numpy as np

from refgs.constants import TILE_SIZE

#: Finite-difference step for :func:`fd_gradient` in float64.  With Richardson extrapolation the
#: truncation error is O(h^4) ~ 1e-16 and the round-off error ~ 1e-16 |f| / h ~ 1e-12 |f|, both far
#: below the 1e-6 relative tolerance the notebooks assert (FD checks in float64).
FD_STEP = 1e-4

#: Demo scene downsampling for the tiny training run: 160 x 120 / 4 = 40 x 30 pixels, small enough
#: for notebook 4 to train two runs within two minutes on two cores; our choice.
TINY_FACTOR = 4
#: Triangulation preset for the tiny run's initial points (refgs.data.triangulate).
TINY_TRIANGULATION = "tuned"


# ---------------------------------------------------------------------------------------------
# Finite differences
# ---------------------------------------------------------------------------------------------

def central_difference(f, x: np.ndarray, h: float) -> np.ndarray:
    """(f(x + h e_k) - f(x - h e_k)) / 2h for every element k of x (any shape, float64)."""
    x = np.array(x, dtype=np.float64)
    grad = np.zeros_like(x)
    flat, g = x.reshape(-1), grad.reshape(-1)
    for k in range(flat.size):
        keep = flat[k]
        flat[k] = keep + h
        up = f(x)
        flat[k] = keep - h
        down = f(x)
        flat[k] = keep
        g[k] = (up - down) / (2 * h)
    return grad


def fd_gradient(f, x: np.ndarray, h: float = FD_STEP) -> np.ndarray:
    """Gradient of the scalar function ``f`` at ``x`` by Richardson-extrapolated central
    differences: (4 D(h/2) - D(h)) / 3, which cancels the h^2 error term of D."""
    return (4 * central_difference(f, x, h / 2) - central_difference(f, x, h)) / 3


def relative_error(analytic, numeric) -> float:
    """max |analytic - numeric| / max |numeric| (0 when both are zero)."""
    a, n = np.asarray(analytic, np.float64), np.asarray(numeric, np.float64)
    scale = float(np.max(np.abs(n))) if n.size else 0.0
    diff = float(np.max(np.abs(a - n))) if a.size else 0.0
    if scale == 0.0:
        return 0.0 if diff == 0.0 else float("inf")
    return diff / scale


# ---------------------------------------------------------------------------------------------
# Ellipses, tiles, clamp regions
# ---------------------------------------------------------------------------------------------

def cov2d_matrix(cov2d_row) -> np.ndarray:
    """(a, b, c) as stored in RenderOutput.cov2d -> [[a, b], [b, c]]."""
    a, b, c = (float(v) for v in cov2d_row)
    return np.array([[a, b], [b, c]])


def ellipse_axes(cov: np.ndarray, n_sigma: float = 1.0) -> tuple[float, float, float]:
    """(full width, full height, angle in degrees) of the n-sigma ellipse of a 2x2 covariance, as
    matplotlib's Ellipse takes them (width along the first eigenvector)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov, np.float64))
    vals = np.maximum(vals, 0.0)
    angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
    return 2 * n_sigma * np.sqrt(vals[1]), 2 * n_sigma * np.sqrt(vals[0]), float(angle)


def add_ellipse(ax, center, cov, n_sigma: float = 1.0, **style):
    """Draw the n-sigma ellipse of ``cov`` (2x2) around ``center`` on ``ax``; returns the patch."""
    from matplotlib.patches import Ellipse

    w, h, ang = ellipse_axes(cov, n_sigma)
    style = {"fill": False, "lw": 1.5, **style}
    patch = Ellipse(tuple(np.asarray(center, float)), w, h, angle=ang, **style)
    ax.add_patch(patch)
    return patch


def draw_tiles(ax, width: int, height: int, rect=None, tile: int = TILE_SIZE, color="tab:orange"):
    """The tile grid of a width x height image; tiles of ``rect`` = (x0, x1, y0, y1) (exclusive
    max, in tiles, as ``project_gaussians``' ``tile_rect``) shaded (RAS-01)."""
    from matplotlib.patches import Rectangle

    for x in range(0, width + 1, tile):
        ax.axvline(min(x, width), color="0.6", lw=0.8)
    for y in range(0, height + 1, tile):
        ax.axhline(min(y, height), color="0.6", lw=0.8)
    if rect is not None:
        x0, x1, y0, y1 = (int(v) for v in rect)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                ax.add_patch(Rectangle((tx * tile, ty * tile), min(tile, width - tx * tile),
                                       min(tile, height - ty * tile), color=color, alpha=0.25))


def clamp_bound(ax, mode: str, scales, **style):
    """Draw, in the Gaussian's principal frame projected on its first two axes, the region the
    FM-04 reading ``mode`` allows for a displacement: ``axis`` and ``box`` the box |l_k| <= s_k,
    ``ellipsoid`` the ellipse ||l / s|| <= 1, ``norm`` the disc ||l|| <= ||s||_2 (3D norm)."""
    from matplotlib.patches import Circle, Ellipse, Rectangle

    s = np.asarray(scales, np.float64)
    style = {"fill": False, "lw": 1.5, "color": "k", **style}
    if mode in ("axis", "box"):
        patch = Rectangle((-s[0], -s[1]), 2 * s[0], 2 * s[1], **style)
    elif mode == "ellipsoid":
        patch = Ellipse((0.0, 0.0), 2 * s[0], 2 * s[1], **style)
    elif mode == "norm":
        patch = Circle((0.0, 0.0), float(np.linalg.norm(s)), **style)
    else:
        raise ValueError(f"mode: expected axis, box, ellipsoid or norm, got {mode!r}")
    ax.add_patch(patch)
    return patch


# ---------------------------------------------------------------------------------------------
# Tables and images
# ---------------------------------------------------------------------------------------------

def text_table(rows, headers) -> str:
    """A fixed-width text table; floats in 3-significant-digit scientific notation."""
    def fmt(v):
        if isinstance(v, (float, np.floating)):
            return f"{float(v):.3e}"
        return str(v)
    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) for i, h in enumerate(headers)]
    line = "  ".join(str(h).ljust(w) for h, w in zip(headers, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(out)


def show_image(ax, img, title: str = "", **kw):
    """imshow of an (H, W, 3) image clipped to [0, 1] (or an (H, W) map as is), no ticks."""
    img = np.asarray(img)
    if img.ndim == 3:
        img = np.clip(img, 0.0, 1.0)
    im = ax.imshow(img, interpolation="nearest", **kw)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    return im


# ---------------------------------------------------------------------------------------------
# The tiny training scene
# ---------------------------------------------------------------------------------------------

def tiny_demo_views(n_views: int = 3, factor: int = TINY_FACTOR, sh_degree: int = 1, seed: int = 0,
                    dtype=np.float64) -> dict:
    """A sparse-view problem small enough for a notebook: the demo scene (DAT-15, built and cached
    by ``refgs.data.demo_scene_path()`` on first use), split with the protocol's rule (DAT-10),
    initial points triangulated from the training views only (DAT-11) at full resolution, and
    images loaded at 1/``factor`` resolution (DAT-05) for training.

    Returns {"train": [View], "test": [View], "gaussians": Gaussians (DAT-13/14),
    "extent": float (TRN-02), "points": (P, 3), "scene": Path}.
    """
    from refgs.data import (demo_scene_path, init_gaussians_from_points, load_scene, split_views,
                            triangulate_train_views)
    from refgs.train.schedule import scene_extent
    from refgs.train.trainer import View

    path = demo_scene_path()
    full = load_scene(path, images="images", dtype=dtype)
    train_idx, test_idx = split_views(full.names, n_views)
    with tempfile.TemporaryDirectory(prefix="refgs-notebook-") as work:
        points, colors = triangulate_train_views(full, train_idx, work, TINY_TRIANGULATION, seed=seed)
    small = load_scene(path, images="images", resolution=factor, dtype=dtype)

    def views(idx):
        return [View(small.names[i], small.cameras[i], small.images[i]) for i in idx]

    train, test = views(train_idx), views(test_idx)
    g = init_gaussians_from_points(points, colors, sh_degree=sh_degree, dtype=dtype)
    return {"train": train, "test": test, "gaussians": g, "points": np.asarray(points),
            "extent": scene_extent([v.camera.center for v in train]), "scene": path}


__all__ = ["FD_STEP", "central_difference", "fd_gradient", "relative_error", "cov2d_matrix",
           "ellipse_axes", "add_ellipse", "draw_tiles", "clamp_bound", "text_table", "show_image",
           "tiny_demo_views"]
