"""One run of a grid, in this process: ``refgs run-one``, a worker of the local executor, a Ray
task.

    execute_run(grid, out, run) -> dict    the outcome: name, state, error, wall_s, host, metrics

Under the run's lock (refgs.sweep.state): a done run is left as it is (not a byte of it is
written); a run whose folder holds other settings is refused (failed, with the reason); a
published run resumes from its checkpoint (refgs.runs.resume); any other starts afresh
(refgs.runs.train), after removing the hidden partial folders a killed run left.  The manifest
says running while it runs, then done, or failed with the error's one line; an interrupted run
(SIGINT / SIGTERM: the trainer writes a checkpoint) goes back to pending.  An exception is
caught and recorded: failures stay with their run.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from .. import runs
from .state import Manifest, disk_state, file_lock, host, lock_path, now, one_line, partial_folders

#: Environment variables that set a run's thread count (numba's pool, OpenMP / BLAS).
THREAD_VARIABLES = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS")
#: Seconds between two looks at whether the parent process is still alive (watch_parent).
PARENT_POLL_S = 1.0
#: Metrics copied into the manifest and the progress line.
SUMMARY_METRICS = ("psnr", "ssim", "lpips_vgg")


def thread_environment(threads: int) -> dict:
    """The environment variables that give a run ``threads`` threads (set before numba loads)."""
    return {k: str(int(threads)) for k in THREAD_VARIABLES}


def watch_parent(parent_pid: int) -> None:
    """Send this process SIGTERM when ``parent_pid`` is no longer its parent (the sweep that
    started it died, even by kill -9): training then writes a checkpoint and stops."""
    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os.kill(os.getpid(), signal.SIGTERM)
    threading.Thread(target=watch, name="refgs-watch-parent", daemon=True).start()


def _outcome(run, state: str, error: str | None = None) -> dict:
    return {"name": run.name, "index": run.index, "state": state, "error": error}


def _summary(folder: Path) -> dict:
    metrics = json.loads((folder / runs.METRICS_FILE).read_text())
    return {k: metrics.get(k) for k in SUMMARY_METRICS}


def execute_run(grid, out: str | os.PathLike, run, progress: bool = False) -> dict:
    """Run ``run`` (a GridRun of ``grid``) in the output folder ``out``; its outcome (name,
    index, state done or failed, error).  Waits while another process holds the run; raises
    runs.Interrupted (state pending) when stopped by SIGINT / SIGTERM."""
    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(out)
    if manifest.read()["runs"].get(run.name, {}).get("settings_hash") != run.settings_hash:
        manifest.refresh(grid)
    with file_lock(lock_path(out, run.name), wait=False) as free:
        if not free:
            print(f"refgs: {run.name}: running in another process; waiting for it",
                  file=sys.stderr)
    with file_lock(lock_path(out, run.name)):
        return _execute_locked(grid, out, manifest, run, progress)


def _execute_locked(grid, out: Path, manifest: Manifest, run, progress: bool) -> dict:
    folder = out / run.name
    state, why = disk_state(out, run)
    entry = manifest.read()["runs"].get(run.name, {})
    if state == "done":
        if entry.get("state") != "done":
            manifest.set_run(run.name, state="done", error=None, metrics=_summary(folder))
        return _outcome(run, "done")
    if state == "changed":
        manifest.set_run(run.name, state="failed", error=why, refused=True, finished=now())
        return _outcome(run, "failed", why)
    manifest.set_run(run.name, state="running", error=None, host=host(), pid=os.getpid(),
                     started=now(), finished=None, attempts=entry.get("attempts", 0) + 1,
                     resumed=state == "resumable")
    t0 = time.perf_counter()
    total = lambda: entry.get("wall_s", 0.0) + time.perf_counter() - t0  # noqa: E731
    try:
        if state == "resumable":
            runs.resume(folder, progress=progress)
        else:
            for leftover in partial_folders(out, run.name):
                shutil.rmtree(leftover)
            runs.train(run.cfg, folder, progress=progress,
                       command=["refgs", "run-one", str(grid.path),
                                "--out", str(out), "--name", run.name])
    except (runs.Interrupted, KeyboardInterrupt, SystemExit):     # it checkpointed: resumable
        manifest.set_run(run.name, state="pending", wall_s=round(total(), 3), finished=now())
        raise
    except Exception as exc:                                    # noqa: BLE001 (stays local)
        error = one_line(f"{type(exc).__name__}: {exc}")
        manifest.set_run(run.name, state="failed", error=error, refused=False,
                         wall_s=round(total(), 3), finished=now())
        return _outcome(run, "failed", error)
    metrics = _summary(folder)
    manifest.set_run(run.name, state="done", error=None, wall_s=round(total(), 3),
                     finished=now(), metrics=metrics)
    return _outcome(run, "done")


__all__ = ["execute_run", "thread_environment", "watch_parent", "THREAD_VARIABLES"]
