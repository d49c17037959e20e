"""Atomic file output: write to a temporary file in the target's folder, then ``os.replace``.

A reader (or a run interrupted by Ctrl-C or ``kill``) therefore sees either the old file or the
complete new one, never a half-written file (house rule; clause TRN-09 of docs/spec/training.md).
The temporary file lives in the same folder so that ``os.replace`` is a rename on one file system.

    atomic_path(path)            context manager yielding a temporary path to write to
    atomic_dir(path)             the same for a whole folder (built beside ``path``, then renamed)
    partial_dir / publish_dir    a folder built over time beside ``path``, renamed when ready
    atomic_write_bytes / _text / _json(path, ...)
    atomic_save_npz(path, arrays)    numpy ``savez`` (readable with ``allow_pickle=False``)
    atomic_save_png(path, image)     (H, W, 3) floats in [0, 1] -> 8-bit PNG
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: Suffix of the temporary files (so that a stray one left by a power cut is recognisable).
TMP_SUFFIX = ".tmp"


def default_mode(directory: bool = False) -> int:
    """Permissions an ordinary ``open``/``mkdir`` would give under the current umask (mkstemp
    and mkdtemp create 0600 / 0700)."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path next to ``path``; on normal exit it replaces ``path`` (fsync'd
    first), on an exception it is removed and ``path`` is left untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    os.chmod(tmp, default_mode())
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_dir(path: str | os.PathLike):
    """Yield a new empty temporary folder next to ``path``; on normal exit it is renamed to
    ``path``, on an exception it is removed with its contents and ``path`` is left untouched.

    ``path`` may be absent or an empty folder (replaced); if it is a non-empty folder when the
    rename comes (e.g. another process published it first) the rename raises ``OSError`` and the
    temporary folder is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=path.parent))
    os.chmod(tmp, default_mode(directory=True))
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def partial_dir(path: str | os.PathLike, tag: str = ".partial-") -> Path:
    """A new empty hidden folder ``.<name><tag>XXXX`` next to ``path`` (the same file system),
    for a folder that is built over time and published later with :func:`publish_dir` (a run
    directory, published at its first checkpoint); the caller removes it if it is never
    published."""
    path = Path(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}{tag}", dir=path.parent))
    os.chmod(tmp, default_mode(directory=True))
    return tmp


def publish_dir(tmp: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Rename the folder ``tmp`` to ``path`` in one step; FileExistsError if ``path`` exists
    (a folder is never replaced)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: already exists")
    os.rename(tmp, path)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj) -> Path:
    """``obj`` as indented JSON (keys in insertion order; NaN/inf refused, as JSON has none)."""
    return atomic_write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def atomic_save_npz(path: str | os.PathLike, arrays: dict) -> Path:
    """``np.savez`` of ``arrays`` (name -> array); object arrays are refused so that the file
    loads with ``np.load(..., allow_pickle=False)`` (house rule: no pickles)."""
    for name, a in arrays.items():
        if np.asarray(a).dtype == object:
            raise ValueError(f"atomic_save_npz: array {name!r} has dtype object (would need pickle)")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    return Path(path)


def to_uint8(image) -> np.ndarray:
    """(H, W, 3) floats -> uint8 ``round(clip(x, 0, 1) * 255)`` (3DGS saves clamped renders)."""
    return np.clip(np.rint(np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255.0),
                   0, 255).astype(np.uint8)


def atomic_save_png(path: str | os.PathLike, image) -> Path:
    """Save an (H, W, 3) image in [0, 1] as an 8-bit PNG (values clamped first)."""
    from PIL import Image

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            Image.fromarray(to_uint8(image)).save(fh, format="PNG")
    return Path(path)


#: Resolution of the analysis pictures (dots per inch).
FIGURE_DPI = 110


def atomic_save_figure(fig, path: str | os.PathLike, dpi: int = FIGURE_DPI) -> Path:
    """Save a matplotlib figure as PNG atomically, then close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return Path(path)


__all__ = ["atomic_path", "atomic_dir", "default_mode", "atomic_write_bytes", "atomic_write_text",
           "atomic_write_json", "atomic_save_npz", "atomic_save_png", "atomic_save_figure",
           "to_uint8", "FIGURE_DPI"]
