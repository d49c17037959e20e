"""refgs.fast.cache: cached kernels are dropped when any source of refgs.fast changes.

numba checks a cached kernel only against the file that defines it; the compositing kernels
inline refgs.fast.fexp, so an edit there must also invalidate kernels.py's cache."""
from pathlib import Path

import pytest

from refgs.fast.cache import MARKER, ensure_fresh_cache, sources_digest


def _package(tmp_path: Path) -> tuple[Path, Path]:
    pkg = tmp_path / "pkg"
    cache = pkg / "__pycache__"
    cache.mkdir(parents=True)
    (pkg / "kernels.py").write_text("x = 1\n")
    (pkg / "fexp.py").write_text("y = 2\n")
    return pkg, cache


def _cached(cache: Path) -> list[Path]:
    files = [cache / "kernels.composite_forward-302.py311.nbi",
             cache / "kernels.composite_forward-302.py311.1.nbc",
             cache / "fexp.fast_exp_array-167.py311.nbi"]
    for f in files:
        f.write_bytes(b"compiled")
    return files


def test_stale_cache_is_removed_and_fresh_cache_kept(tmp_path):
    pkg, cache = _package(tmp_path)
    files = _cached(cache)
    other = cache / "kernels.cpython-311.pyc"          # not numba's: left alone
    other.write_bytes(b"pyc")
    assert ensure_fresh_cache(pkg, cache) is True        # no marker yet: built from unknown sources
    assert not any(f.exists() for f in files) and other.exists()
    assert (cache / MARKER).read_text().strip() == sources_digest(pkg)

    files = _cached(cache)                                # compiled again from these sources
    assert ensure_fresh_cache(pkg, cache) is False
    assert all(f.exists() for f in files)

    (pkg / "fexp.py").write_text("y = 3\n")              # an inlined dependency changes
    assert ensure_fresh_cache(pkg, cache) is True
    assert not any(f.exists() for f in files)


def test_no_cache_dir_is_a_no_op(tmp_path):
    pkg, _ = _package(tmp_path)
    assert ensure_fresh_cache(pkg, None) is False


def test_import_records_the_sources_of_the_installed_package():
    pytest.importorskip("numba")
    import refgs.fast as fast
    from refgs.fast.cache import cache_dir_of
    from refgs.fast import kernels

    cache = cache_dir_of(kernels.composite_forward)
    marker = cache / MARKER
    if marker.is_file():                                 # a read-only install may have none
        assert marker.read_text().strip() == sources_digest(Path(fast.__file__).parent)
