"""Keep numba's on-disk kernel cache in step with the sources of refgs.fast.

numba (``cache=True``) checks a cached kernel against the modification time and size of the one
file that defines it, not against the functions it inlines from other files: after an edit of
``fexp.py`` the compositing kernels of ``kernels.py`` would keep loading the machine code built
with the old exp (a changed polynomial would have no effect until ``__pycache__`` is
cleared).  :func:`ensure_fresh_cache` closes that gap: it hashes every source file of this
package and, when the hash differs from the one recorded beside the cache, deletes the package's
cached kernels (``*.nbi`` index and ``*.nbc`` code files) so that they are compiled again from
the current sources; then it records the new hash.  It runs once, when refgs.fast is imported;
it only touches numba's own cache files of this package, and a cache folder it cannot write is
left alone (numba then falls back to compiling in memory).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from ..io.atomic import atomic_write_text

#: file beside the cached kernels holding the SHA-256 of the package sources they were built from
MARKER = "refgs-fast-sources.sha256"


def sources_digest(package_dir: Path) -> str:
    """SHA-256 over the names and bytes of the package's ``*.py`` files, in name order."""
    h = hashlib.sha256()
    for path in sorted(package_dir.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def cache_dir_of(dispatcher) -> Path | None:
    """Where numba caches ``dispatcher`` (honours NUMBA_CACHE_DIR); None if unknown."""
    path = getattr(getattr(dispatcher, "_cache", None), "_cache_path", None)
    return Path(path) if path else None


def ensure_fresh_cache(package_dir: Path, cache_dir: Path | None) -> bool:
    """Delete this package's cached kernels in ``cache_dir`` if they were built from other
    sources (module docstring).  Returns True when files were deleted."""
    if cache_dir is None:
        return False
    digest = sources_digest(package_dir)
    marker = cache_dir / MARKER
    try:
        if marker.is_file() and marker.read_text().strip() == digest:
            return False
        modules = {p.stem for p in package_dir.glob("*.py")}
        removed = False
        if cache_dir.is_dir():
            for f in cache_dir.iterdir():
                if f.suffix in (".nbi", ".nbc") and f.name.split(".", 1)[0] in modules:
                    f.unlink(missing_ok=True)
                    removed = True
        atomic_write_text(marker, digest + "\n")
        return removed
    except OSError:
        return False


__all__ = ["ensure_fresh_cache", "sources_digest", "cache_dir_of", "MARKER"]
