"""Checkpoints and the provenance a run records (clause TRN-09, docs/spec/training.md).

A checkpoint is one ``.npz`` of plain arrays, readable with ``np.load(..., allow_pickle=False)``:
parameters ``param/<name>``, Adam moments and step counts ``adam/...``, densification statistics
``densify/...``, curves ``history/...``, method state ``method/...``, and ``meta``: a 0-d string
holding JSON (iteration, the bit-generator states of the run's random streams, the training-view
stack, timings).  numpy's PCG64 state is a dict of integers, so it round-trips through JSON
exactly; no pickle is ever written or read.

The run directory that holds a checkpoint (its files, how it is created, published and read
back) is refgs.runs.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

from ..errors import RefgsError
from ..io.atomic import atomic_save_npz

#: Format version stored in every checkpoint's meta; loading another version is refused.
CHECKPOINT_VERSION = 1


class CheckpointError(RefgsError):
    """A checkpoint or run directory is missing, corrupt or from another version."""


# --- random streams -------------------------------------------------------------------------
def rng_state(rng: np.random.Generator) -> dict:
    """The bit generator's state as a JSON-able dict (PCG64: big integers, exact in JSON)."""
    return rng.bit_generator.state


def rng_from_state(state: dict) -> np.random.Generator:
    name = state.get("bit_generator")
    if name != "PCG64":
        raise CheckpointError(f"checkpoint: unsupported bit generator {name!r} (expected PCG64)")
    bg = np.random.PCG64()
    bg.state = state
    return np.random.Generator(bg)


# --- checkpoint file ------------------------------------------------------------------------
def save_checkpoint(path: str | Path, arrays: dict, meta: dict) -> Path:
    """Write ``arrays`` and ``meta`` (JSON-able) atomically as an npz (TRN-09)."""
    if "meta" in arrays:
        raise ValueError("save_checkpoint: 'meta' is reserved")
    meta = dict(meta, version=CHECKPOINT_VERSION)
    data = dict(arrays)
    data["meta"] = np.array(json.dumps(meta))
    return atomic_save_npz(path, data)


def load_checkpoint(path: str | Path) -> tuple[dict, dict]:
    """``(arrays, meta)`` from a checkpoint written by save_checkpoint; CheckpointError naming the
    file when it is missing, truncated, not an npz, needs pickle, or has another version."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    if "meta" not in arrays:
        raise CheckpointError(f"{path}: not a refgs checkpoint (no 'meta' entry)")
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except ValueError:
        raise CheckpointError(f"{path}: checkpoint meta is not valid JSON") from None
    if meta.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {meta.get('version')!r}, this refgs "
                              f"reads version {CHECKPOINT_VERSION}")
    return arrays, meta


# --- provenance -----------------------------------------------------------------------------
def _git(args: list[str], cwd: Path) -> str | None:
    try:
        res = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() if res.returncode == 0 else None


def cpu_name() -> str:
    """The CPU's model name (/proc/cpuinfo), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


#: The float-environment fields that decide the bytes of a float computation on one machine
#: (docs/spec/training.md TRN-13): numpy's ufunc dispatch level, its BLAS kernel, the CPU that
#: numba compiles for. Two machines that agree on all of them give the same bytes.
FLOAT_ENV_FIELDS = ("numpy", "numpy_simd", "blas", "numba_cpu")


def numpy_simd_level() -> str:
    """The highest of numpy's dispatch targets (``__cpu_dispatch__``: X86_V3 = AVX2, X86_V4 =
    AVX-512, ...) this CPU runs, else numpy's baseline; what ``np.show_runtime()`` calls found."""
    try:
        from numpy._core._multiarray_umath import (__cpu_baseline__, __cpu_dispatch__,
                                                   __cpu_features__)
    except ImportError:                                    # numpy < 2
        from numpy.core._multiarray_umath import (__cpu_baseline__, __cpu_dispatch__,
                                                  __cpu_features__)
    found = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    return found[-1] if found else (__cpu_baseline__[-1] if __cpu_baseline__ else "none")


def blas_kernel() -> str | None:
    """numpy's BLAS and the kernel set it chose at run time (e.g. "openblas 0.3.31 Haswell"),
    read by threadpoolctl; None when it cannot tell."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    for lib in threadpool_info():
        if lib.get("user_api") == "blas" and "numpy" in str(lib.get("filepath", "")):
            return " ".join(str(lib.get(k)) for k in ("internal_api", "version", "architecture"))
    return None


def numba_cpu() -> str | None:
    """The CPU numba compiles the fast backend for (``NUMBA_CPU_NAME``, else LLVM's host CPU),
    None without llvmlite."""
    if os.environ.get("NUMBA_CPU_NAME"):
        return os.environ["NUMBA_CPU_NAME"]
    try:
        from llvmlite import binding
    except ImportError:
        return None
    return binding.get_host_cpu_name()


def float_environment() -> dict:
    """The machine facts that decide float bytes (FLOAT_ENV_FIELDS): a record is comparable bit
    for bit only with records of the same float environment (TRN-13)."""
    import numpy
    return {"numpy": numpy.__version__, "numpy_simd": numpy_simd_level(),
            "blas": blas_kernel(), "numba_cpu": numba_cpu()}


def float_environment_key(env: dict | None = None) -> str:
    """``float_environment()`` (or ``env``) as one line, fields in FLOAT_ENV_FIELDS order: the key
    under which a machine's bit-for-bit digests are pinned (TRN-13)."""
    env = float_environment() if env is None else env
    return "; ".join(f"{k} {env.get(k)}" for k in FLOAT_ENV_FIELDS)


def peak_rss_gb() -> float:
    """This process's peak resident memory in GB (``ru_maxrss``: KiB on Linux, bytes on macOS)."""
    import resource
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 ** 3 if sys.platform == "darwin" else 1024 ** 2)


def source_hash() -> str:
    """sha256 (16 hex digits) of every ``refgs/**/*.py`` file's path and bytes: a resume compares
    it with the run's to warn when the code changed (bitwise equality needs the same code)."""
    import hashlib

    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def provenance() -> dict:
    """git hash (None outside a git checkout / before the first commit), dirty flag, package
    versions, CPU and its float environment (SIMD level, BLAS kernel), thread settings, Python and
    platform (recorded in config.json)."""
    from importlib import metadata

    root = Path(__file__).resolve().parents[2]
    versions = {}
    for pkg in ("refgs", "numpy", "scipy", "scikit-image", "pycolmap", "plyfile", "matplotlib",
                "tqdm", "pillow"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    status = _git(["status", "--porcelain", "--untracked-files=no"], root)
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    return {
        "git_hash": _git(["rev-parse", "HEAD"], root),
        "source_hash": source_hash(),
        "git_dirty": None if status is None else bool(status),
        "packages": versions,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "float_environment": float_environment(),
        "threads_available": affinity,
        "thread_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                        "MKL_NUM_THREADS")},
    }


__all__ = ["save_checkpoint", "load_checkpoint", "provenance", "source_hash", "peak_rss_gb",
           "cpu_name", "float_environment", "float_environment_key", "numpy_simd_level", "blas_kernel", "numba_cpu",
           "FLOAT_ENV_FIELDS", "rng_state", "rng_from_state", "CheckpointError", "CHECKPOINT_VERSION"]
