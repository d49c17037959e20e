"""Records from equivalent code: ``refgs report GRID --check-equivalence [--reference-code DIR]``.

A report counts the records of the training code its grid accepts (``[[report.code]]``: source
hashes, refgs.train.checkpoint.source_hash, which changes with any byte of refgs/).  Code that
changed only in ways that leave training bit-identical (speed work, docs, analysis) should not
strand the records, so a new source hash is accepted when it reproduces the grid's *pinned run*
bit for bit: ``[report.equivalence]`` holds the ``refgs train`` options of a short run (a few
dozen iterations of a small scene, with densification and the method's re-initialisation inside
it), and the run's digest -- sha256 of its final model's vertex data (model.ply) -- must equal the
digest accepted code gives.

Float results differ between machines of different float environments (docs/spec/training.md
TRN-13: numpy's SIMD level and BLAS kernel, the CPU numba compiles for), so the accepted digest is
pinned per float environment (``float_environment``: refgs.train.checkpoint.float_environment_key)
in ``[[report.equivalence.pin]]`` entries.  On an environment with no pin yet, ``--reference-code DIR`` (a
checkout of code the grid accepts, e.g. ``git archive COMMIT refgs | tar -x -C DIR``) makes the
pinned run on this machine first, and its digest becomes the level's pin: the new code is then
compared with accepted code side by side.  An accepted hash is appended to the grid file as a
``[[report.code]]`` entry saying how it was accepted; code that differs is refused (ConfigError
naming both digests).
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import tomllib
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_write_text
from ..train.checkpoint import float_environment_key, source_hash
from .report_spec import Report, load_report

#: The run's model, whose vertex data is digested (refgs.runs writes it at the end of a run).
MODEL_FILE = "model.ply"
#: Lines of a failed run's stderr quoted in the error.
STDERR_TAIL = 3
SOURCE_HASH_CODE = "from refgs.train.checkpoint import source_hash; print(source_hash())"


def model_digest(path: Path) -> str:
    """sha256 of the vertex data of a 3DGS PLY (property names, types and values; not the
    header's comments)."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"].data
    h = hashlib.sha256(repr(vertex.dtype.descr).encode())
    h.update(np.ascontiguousarray(vertex).tobytes())
    return h.hexdigest()


def code_root() -> Path:
    """The folder holding this refgs package (what PYTHONPATH must name to run it)."""
    return Path(__file__).resolve().parents[2]


def run_code(root: Path, argv: list[str], out: Path) -> tuple[str, str]:
    """(model digest, source hash) of the pinned run made by the refgs under ``root`` in a
    fresh process; ConfigError with the end of its stderr when it fails."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(root)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])))
    cmd = [sys.executable, "-m", "refgs", "train", *argv, "--out", str(out), "--quiet"]
    # run outside any checkout: the current folder would come before PYTHONPATH on sys.path
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=out.parent)
    if done.returncode != 0 or not (out / MODEL_FILE).is_file():
        tail = " | ".join(done.stderr.strip().splitlines()[-STDERR_TAIL:])
        raise ConfigError(f"the pinned run with the code in {root} failed (exit "
                          f"{done.returncode}): {tail}")
    code = subprocess.run([sys.executable, "-c", SOURCE_HASH_CODE], env=env, cwd=out.parent,
                          capture_output=True, text=True, check=True).stdout.strip()
    return model_digest(out / MODEL_FILE), code


def toml_string(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def append_entry(grid: Path, table: str, entry: dict) -> None:
    """Append a ``[[table]]`` entry of string values to the grid file (atomically), checking the
    file still loads as a report."""
    text = grid.read_text(encoding="utf-8").rstrip("\n")
    lines = [f"[[{table}]]"] + [f"{k} = {toml_string(v)}" for k, v in entry.items()]
    new = text + "\n\n" + "\n".join(lines) + "\n"
    tomllib.loads(new)
    atomic_write_text(grid, new)
    load_report(grid)


def today() -> str:
    return datetime.now(timezone.utc).date().isoformat()


def check_equivalence(report: Report, reference_code: str | None = None) -> str:
    """Accept this checkout's training code for the report's grid when its pinned run gives the
    pinned digest (module docstring); the one-line verdict, or ConfigError."""
    if report.equivalence is None:
        raise ConfigError(f"{report.grid}: no [report.equivalence] table (the pinned run that "
                          "checks new code: docs/sweeps.md)")
    current = source_hash()
    if current in report.code:
        return f"{current}: already accepted by {report.name}"
    argv, pins = report.equivalence
    accepted = ", ".join(report.code) or "none"
    level = float_environment_key()
    pinned = {env: (digest, code) for env, digest, code in pins}
    with tempfile.TemporaryDirectory(prefix="refgs-equivalence-") as tmp:
        if level not in pinned:
            if reference_code is None:
                raise ConfigError(f"--reference-code: {report.grid} has no pinned digest for the "
                                  f"float environment {level}; give a checkout of accepted code ({accepted}) "
                                  "to pin it on this machine")
            digest, code = run_code(Path(reference_code).absolute(), list(argv),
                                    Path(tmp) / "reference")
            if code not in report.code:
                raise ConfigError(f"--reference-code: {reference_code} holds code {code}, not "
                                  f"code {report.name} accepts ({accepted})")
            append_entry(report.grid, "report.equivalence.pin",
                         {"float_environment": level, "digest": digest, "code": code, "date": today()})
            pinned[level] = (digest, code)
        digest, code = run_code(code_root(), list(argv), Path(tmp) / "current")
    want, by = pinned[level]
    if digest != want:
        raise ConfigError(f"{report.name}: code {code} does not reproduce the pinned run on the "
                          f"float environment {level} (model digest {digest[:16]}, accepted code {by} gives "
                          f"{want[:16]}): its records do not count; rerun them with code "
                          f"{report.name} accepts")
    append_entry(report.grid, "report.code", {
        "hash": code, "how": f"reproduces the pinned run ([report.equivalence]) bit for bit on "
                             f"float environment {level}: model digest {digest[:16]}, as code {by}",
        "date": today()})
    return f"{code}: accepted by {report.name} (same pinned run as {by} on {level})"


__all__ = ["check_equivalence", "model_digest", "run_code", "append_entry"]
