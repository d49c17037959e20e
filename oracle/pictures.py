"""Pictures of a failing case for the report page (ORC-13): matplotlib (Agg), PNG files.

    pictures = draw(evidence, folder, "forward_pixel_centres")   # [(file name, caption), ...]

``evidence`` is what the runner keeps of a failure (runner.CheckResult.evidence): the smallest
case and the reference's and the backend's outputs on it, as captured by oracle/evaluate.py.
Drawn, when the evidence has them:

* ``<stem>-image.png``: rows image and alpha; columns the reference, the backend, and
  |backend - reference| as a heat map with its colour bar (the image's difference is the
  largest over RGB).  A backend output that is missing, malformed or of the wrong shape is a
  panel saying so; non-finite pixels are drawn magenta.
* ``<stem>-gaussians.png``: per Gaussian, the error of each gradient field (or stage output)
  relative to the Gaussian's own size, max|g_i - r_i| / max|r_i| (the row scale of ORC-03), as a
  grid of fields x Gaussians coloured by its logarithm.

Files are written atomically next to the page.
"""
from __future__ import annotations

import io
import textwrap
from pathlib import Path

import numpy as np

from refgs.io.atomic import atomic_write_bytes

from .protocol import get_field

#: folder of the pictures, relative to the report page beside it (index.html, diagnosis.html)
PICTURES = "pictures"
#: colour of non-finite pixels and of panels without data
BAD_COLOUR = "magenta"
#: figure width per panel and height per row (inches) and resolution (dots per inch)
PANEL_IN, ROW_IN, DPI = 2.6, 2.2, 80
#: characters per line of a panel's text
PANEL_CHARS = 30
#: smallest row size a relative per-Gaussian error is taken against
TINY = 1e-30
#: a reference whose largest value is below this is drawn brightened to its largest value
FAINT = 0.25
#: the per-Gaussian error grid's colour scale starts here (relative error; float64 rounding)
LOG_FLOOR = 1e-16
#: the grid prints each error when there are at most this many Gaussians
ANNOTATE_MAX = 12


def _pyplot():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def _array(obj, name):
    try:
        val = get_field(obj, name)
    except Exception:
        return None
    return val if isinstance(val, np.ndarray) else None


def _panel_text(ax, text: str) -> None:
    ax.text(0.5, 0.5, textwrap.fill(text, PANEL_CHARS), ha="center", va="center", fontsize=7,
            transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def _gain(ref) -> float:
    """Display gain for a faint reference: 1, or 1 / its largest value when that is below
    :data:`FAINT` (so that a few percent of alpha is still visible)."""
    top = float(np.nanmax(np.abs(ref))) if np.size(ref) and np.isfinite(ref).any() else 0.0
    return 1.0 / top if 0.0 < top < FAINT else 1.0


def _show(ax, img, title: str, plt, gain: float = 1.0) -> None:
    img = np.asarray(img, np.float64) * gain
    if gain != 1.0:
        title += f" (x{gain:.3g})"
    finite = np.isfinite(img)
    shown = np.clip(np.where(finite, img, 0.0), 0.0, 1.0)
    if img.ndim == 3:
        shown[~np.all(finite, axis=-1)] = (1.0, 0.0, 1.0)
        ax.imshow(shown, interpolation="nearest")
    else:
        cmap = plt.get_cmap("gray").with_extremes(bad=BAD_COLOUR)
        ax.imshow(np.ma.masked_invalid(img).clip(0, 1), cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
    ax.set_title(title, fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])


def _diff(ax, got, ref, label: str, plt, fig) -> None:
    d = np.abs(np.asarray(got, np.float64) - np.asarray(ref, np.float64))
    if d.ndim == 3:
        d = np.where(np.any(~np.isfinite(d), axis=-1), np.nan, np.max(d, axis=-1))
    cmap = plt.get_cmap("inferno").with_extremes(bad=BAD_COLOUR)
    top = float(np.nanmax(d)) if np.isfinite(d).any() else 0.0
    im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, interpolation="nearest", vmin=0.0,
                   vmax=top if top > 0 else 1.0)
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    cb.ax.tick_params(labelsize=6)
    worst = np.nanmax(d) if np.isfinite(d).any() else float("nan")
    ax.set_title(f"|{label} diff|, max {worst:.3g}", fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])


def _why_missing(got, name: str, shape) -> str:
    if got is None:
        return f"{name}: the backend returned nothing"
    val = get_field(got, name)
    if val is None:
        return f"{name} is missing from the backend's output"
    if not isinstance(val, np.ndarray):
        return getattr(val, "message", f"{name} is malformed")
    return f"{name}.shape={tuple(val.shape)}, but should be {tuple(shape)}"


def _save(fig, path: Path, plt) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def image_figure(ref, got, path: Path, note: str = "") -> Path:
    """Reference, backend and |difference| for image and alpha (module docstring)."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(3 * PANEL_IN, 2 * ROW_IN), squeeze=False)
    for row, name in enumerate(("image", "alpha")):
        r = np.asarray(getattr(ref, name))
        gain = _gain(r)
        _show(axes[row, 0], r, f"reference {name}", plt, gain)
        g = _array(got, name) if got is not None else None
        if g is not None and g.shape == r.shape:
            _show(axes[row, 1], g, f"backend {name}", plt, gain)
            _diff(axes[row, 2], g, r, name, plt, fig)
        else:
            why = note or _why_missing(got, name, r.shape)
            _panel_text(axes[row, 1], "backend " + name + ":\n" + why)
            _panel_text(axes[row, 2], "no difference to show")
    _save(fig, path, plt)
    return path


def gaussian_figure(ref: dict, got: dict, path: Path, title: str) -> Path | None:
    """Per-Gaussian relative error of every field both sides have, as a grid (fields x
    Gaussians) coloured by log10 of the error and annotated with it (module docstring)."""
    rows = []
    for name, r in ref.items():
        g = got.get(name) if isinstance(got, dict) else _array(got, name)
        r = np.asarray(r)
        if r.ndim == 0 or r.shape[0] == 0 or r.dtype.kind == "b":
            continue
        if isinstance(g, np.ndarray) and g.shape == r.shape:
            rr = np.abs(r.astype(np.float64)).reshape(r.shape[0], -1)
            dd = np.abs(g.astype(np.float64) - r.astype(np.float64)).reshape(r.shape[0], -1)
            rows.append((name, np.max(dd, axis=1) / np.maximum(np.max(rr, axis=1), TINY)))
    if not rows:
        return None
    err = np.stack([e for _, e in rows])
    shown = np.log10(np.where(np.isfinite(err), err, np.nan) + LOG_FLOOR)
    plt = _pyplot()
    n = err.shape[1]
    fig, ax = plt.subplots(figsize=(min(2.0 + 0.6 * n, 14.0), 0.45 * len(rows) + 1.2))
    cmap = plt.get_cmap("viridis").with_extremes(bad=BAD_COLOUR)
    im = ax.imshow(np.ma.masked_invalid(shown), cmap=cmap, aspect="auto", interpolation="nearest",
                   vmin=np.log10(LOG_FLOOR), vmax=max(0.0, float(np.nanmax(shown)) if np.isfinite(shown).any() else 0.0))
    if n <= ANNOTATE_MAX:
        for (i, j), e in np.ndenumerate(err):
            ax.text(j, i, "nan" if not np.isfinite(e) else f"{e:.1e}", ha="center", va="center",
                    fontsize=6, color="white" if not np.isfinite(e) or e < 1e-3 else "black")
    ax.set_yticks(range(len(rows)), [name for name, _ in rows], fontsize=7)
    ax.set_xticks(range(n), [str(j) for j in range(n)], fontsize=6)
    ax.set_xlabel("Gaussian", fontsize=7)
    ax.set_title(title, fontsize=8)
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    cb.set_label("log10 max|backend - ref| / max|ref|", fontsize=6)
    cb.ax.tick_params(labelsize=6)
    _save(fig, path, plt)
    return path


def _grad_dict(grads) -> dict:
    if grads is None:
        return {}
    names = ("means", "log_scales", "quats", "opacity_logits", "sh", "means2d")
    out = {}
    for n in names:
        val = _array(grads, n)
        if val is not None:
            out[n] = val
    return out


def draw(evidence: dict | None, folder, stem: str, note: str = "") -> list[tuple[str, str]]:
    """The pictures of one failure, written to ``folder``; ``[(file name, caption)]``.
    ``note`` replaces the backend's panels (e.g. why the worker has no output)."""
    if not evidence:
        return []
    folder = Path(folder)
    out = []
    fwd = evidence.get("forward", {})
    stage = evidence.get("stage", {})
    if "ref" in fwd:
        p = image_figure(fwd["ref"], fwd.get("got"), folder / f"{stem}-image.png", note)
        out.append((p.name, "reference, backend and |difference| (image: largest over RGB; magenta: "
                            "not finite)"))
    elif "image" in stage.get("ref", {}):
        class _R:
            image = stage["ref"]["image"]
            alpha = stage["ref"]["alpha"]
        p = image_figure(_R, stage.get("got", {}), folder / f"{stem}-image.png", note)
        out.append((p.name, "stage_composite: reference, backend and |difference|"))
    bwd = evidence.get("backward", {})
    if "ref" in bwd and "got" in bwd:
        p = gaussian_figure(_grad_dict(bwd["ref"]), _grad_dict(bwd["got"]),
                            folder / f"{stem}-gaussians.png", "gradients: error per Gaussian")
        if p is not None:
            out.append((p.name, "per-Gaussian gradient error, relative to the Gaussian's largest "
                                "reference entry"))
    elif stage.get("ref") and "image" not in stage["ref"]:
        p = gaussian_figure(stage["ref"], stage.get("got", {}), folder / f"{stem}-gaussians.png",
                            "stage outputs: error per Gaussian")
        if p is not None:
            out.append((p.name, "per-Gaussian error of the stage's outputs"))
    return out
