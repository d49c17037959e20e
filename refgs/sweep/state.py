"""Where a sweep stands, read from the filesystem: run directories, run locks and the manifest.

The output folder DIR of a sweep holds

    DIR/<name>/            one run directory per run of the grid (refgs.runs)
    DIR/sweep.json         the manifest: every run's settings, state, error line, wall time, host
    DIR/.sweep/locks/      one lock file per run, held (flock) by the process running it
    DIR/.sweep/logs/       the output of each run (the local executor's worker processes)

The run directories are the truth; the manifest records it for people and tools.  A run is

    done       its metrics.json exists and its config.json has the grid's settings hash
    changed    its folder holds another run (other settings, or no run at all): refused
    resumable  published (it reached its first checkpoint) with the grid's settings, not done
    new        no folder yet (a hidden ``.<name>.partial-*`` folder left by a killed run is
               removed when the run starts again)

A lock is released by the kernel when its holder dies, however it dies, so a stale ``running``
in the manifest (a sweep killed with kill -9) is recognised and the run resumed.  The manifest is
changed only under its own lock (read, change, atomic write), so several processes -- the sweep,
its workers, the tasks of a SLURM array -- can share it.  flock is POSIX: on a shared file system
it needs working locks (NFSv4, or NFSv3 with lockd; docs/sweeps.md).
"""
from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from contextlib import contextmanager
from pathlib import Path

from ..errors import ConfigError
from ..io.atomic import atomic_write_json
from ..runs import CHECKPOINT_FILE, METRICS_FILE, PARTIAL_TAG, read_config, settings_hash
from ..train.checkpoint import CheckpointError

#: The manifest, and the hidden folder of locks and logs, in a sweep's output folder.
MANIFEST_FILE = "sweep.json"
HIDDEN_DIR = ".sweep"
#: The states of a run in the manifest.
STATES = ("pending", "running", "done", "failed")
#: Manifest format version.
MANIFEST_VERSION = 1


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def one_line(text) -> str:
    return " ".join(str(text).split())


# --- the filesystem ------------------------------------------------------------------------------
def disk_state(out: Path, run) -> tuple[str, str]:
    """(state, why) of ``run`` (a GridRun) in the output folder ``out``: state is done, changed,
    resumable or new (module docstring); ``why`` says what was found."""
    folder = Path(out) / run.name
    if not folder.exists():
        leftovers = partial_folders(out, run.name)
        return "new", (f"{len(leftovers)} partial folder(s) of a killed run" if leftovers else "")
    try:
        config = read_config(folder)
    except CheckpointError as exc:
        return "changed", (f"{folder} exists but is not a run directory of this grid ({exc}); "
                           "move it away to run it")
    recorded = config.get("settings_hash")
    if recorded != run.settings_hash or settings_hash(config.get("settings", {})) != recorded:
        return "changed", (f"{folder} was run with other settings (settings hash {recorded}, the "
                           f"grid's {run.settings_hash}): the grid changed since; refusing to "
                           "overwrite it (move it away, or restore the grid)")
    if (folder / METRICS_FILE).is_file():
        return "done", ""
    if not (folder / CHECKPOINT_FILE).is_file():
        return "changed", f"{folder}: {CHECKPOINT_FILE} missing; move the folder away to run it"
    return "resumable", "resumes from its checkpoint"


def partial_folders(out: Path, name: str) -> list[Path]:
    """The hidden folders a run named ``name`` was being built in (refgs.runs.RunDir)."""
    return sorted(Path(out).glob(f".{name}{PARTIAL_TAG}*"))


# --- locks ---------------------------------------------------------------------------------------
def lock_path(out: Path, name: str) -> Path:
    return Path(out) / HIDDEN_DIR / "locks" / f"{name}.lock"


def log_path(out: Path, name: str) -> Path:
    return Path(out) / HIDDEN_DIR / "logs" / f"{name}.log"


@contextmanager
def file_lock(path: Path, wait: bool = True):
    """Hold an exclusive flock on ``path`` (created if absent) for the block; yields True, or
    False at once when ``wait`` is False and another process holds it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def is_locked(out: Path, name: str) -> bool:
    """Whether a process holds the run's lock now (is running it)."""
    path = lock_path(out, name)
    if not path.is_file():
        return False
    with file_lock(path, wait=False) as got:
        return not got


# --- the manifest --------------------------------------------------------------------------------
class Manifest:
    """DIR/sweep.json, read and changed under DIR/.sweep/sweep.lock.

    read()                     the manifest (an empty one if absent)
    update(change)             change(data) under the lock, then an atomic write
    set_run(name, **fields)    update one run's entry
    refresh(grid)              one entry per run of ``grid``, states taken from the filesystem
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out).absolute()
        self.path = self.out / MANIFEST_FILE
        self.lock = self.out / HIDDEN_DIR / "sweep.lock"

    def read(self) -> dict:
        if not self.path.is_file():
            return {"version": MANIFEST_VERSION, "grid": None, "runs": {}}
        try:
            return json.loads(self.path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{self.path}: not valid JSON ({exc}); remove it (it is rebuilt "
                              "from the run directories)") from None

    def update(self, change) -> dict:
        with file_lock(self.lock):
            data = self.read()
            change(data)
            data["updated"] = now()
            atomic_write_json(self.path, data)
        return data

    def set_run(self, name: str, **fields) -> dict:
        def change(data):
            data["runs"].setdefault(name, {}).update(fields)
        return self.update(change)

    def refresh(self, grid, retry_failed: bool = False) -> dict:
        """One entry per run of ``grid`` (runs no longer in it are dropped), in the state
        :func:`current` finds; the rest of an entry (wall time, attempts, host) is kept while
        the run's settings are the same."""
        def change(data):
            old = data.get("runs", {})
            data.update(version=MANIFEST_VERSION, grid=str(grid.path))
            data["runs"] = {r.name: entry(r, old.get(r.name, {})) for r in grid.runs}

        def entry(run, prev):
            if prev.get("settings_hash") != run.settings_hash:
                prev = {}
            state, error, _ = current(self.out, run, prev, retry_failed)
            return {"index": run.index, "settings_hash": run.settings_hash,
                    "options": run.options, "state": state, "error": error,
                    "refused": state == "failed" and disk_state(self.out, run)[0] == "changed",
                    **{k: prev.get(k, d) for k, d in KEPT.items()}}

        return self.update(change)


#: Fields of a manifest entry kept from one sweep to the next, with their initial values.
KEPT = {"wall_s": 0.0, "attempts": 0, "host": None, "pid": None, "started": None,
        "finished": None, "metrics": None}


def current(out: Path, run, prev: dict, retry_failed: bool = False) -> tuple:
    """(state, error, plan) of ``run`` now, from the filesystem, its lock and its previous
    manifest entry ``prev``: done (skip); failed with the refusal when its folder holds other
    settings; running while another process holds it; failed again when it failed before (a
    failure, not a refusal) unless ``retry_failed``; else pending (resume, or start)."""
    disk, why = disk_state(out, run)
    if disk == "done":
        return "done", None, "skip: done"
    if disk == "changed":
        return "failed", why, f"refuse: {why}"
    if is_locked(out, run.name):
        return "running", None, "wait: running in another process"
    if (prev.get("state") == "failed" and not prev.get("refused") and not retry_failed
            and prev.get("settings_hash") == run.settings_hash):
        return "failed", prev.get("error"), "skip: failed before (--retry-failed runs it again)"
    if disk == "resumable":
        return "pending", None, "resume from its checkpoint"
    return "pending", None, "start" + (f" (removing the {why})" if why else "")


def counts(data: dict) -> dict:
    """Runs per state in a manifest."""
    out = {s: 0 for s in STATES}
    for e in data.get("runs", {}).values():
        out[e.get("state", "pending")] = out.get(e.get("state", "pending"), 0) + 1
    return out


def host() -> str:
    return socket.gethostname()


__all__ = ["Manifest", "current", "disk_state", "partial_folders", "file_lock", "is_locked",
           "lock_path", "log_path", "counts", "host", "now", "one_line", "MANIFEST_FILE",
           "HIDDEN_DIR", "STATES"]
