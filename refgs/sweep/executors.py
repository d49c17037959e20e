"""The sweep: the runs of a grid that are not done, on a local process pool or on Ray.

    sweep(grid, out, executor, workers, threads, retry_failed) -> dict    the final manifest
    plan(grid, out, retry_failed) -> [(run, state, what)]                 what a sweep would do

Executors (each yields the outcome of a run as it finishes, refgs.sweep.execute):

    local  ``workers`` worker processes at a time, each ``python -m refgs run-one ... --name N``
           with ``threads`` threads (execute.THREAD_VARIABLES set in its environment before numba
           loads); its output goes to DIR/.sweep/logs/<name>.log.  A worker that dies (killed,
           out of memory) leaves its run failed with the reason; the other runs go on.  The
           workers stop (checkpoint and exit) when the sweep dies.
    ray    one Ray task per run with num_cpus = ``threads`` (the same variables through the
           task's runtime_env), retried by Ray when its worker is lost; RAY_ADDRESS when set,
           else a local Ray started for the sweep with ``workers * threads`` CPUs.  A cluster
           that does not answer at RAY_ADDRESS within ``--ray-timeout`` seconds (default
           DEFAULT_RAY_TIMEOUT_S) ends the sweep with one line naming the address.  The output
           folder and the scenes must be on a file system every node sees at the same path.

A run's result does not depend on the executor, the number of workers or threads: the same
settings and seed give the same model.ply bytes (the fast backend is bit-identical for any thread
count, refgs.fast.render).  One line is printed per run as it finishes, under a bar of the runs
(done / running / failed, the ETA from the finished runs).
"""
from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path

from .. import runs
from ..errors import ConfigError
from .execute import execute_run, thread_environment
from .grid import load_grid
from .state import Manifest, counts, current, host, log_path, one_line

EXECUTORS = ("local", "ray")
#: Threads per run by default (runs in parallel use the cores better than threads in one run).
DEFAULT_THREADS = 1
#: Seconds between two refreshes of the progress bar while no run finishes.
POLL_S = 1.0
#: Times Ray runs a task again when its worker process or node is lost (Ray's default is 3).
RAY_MAX_RETRIES = 3
#: Exit status of ``refgs run-one`` when its run was interrupted (refgs.cli: 128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Seconds ``--executor ray`` waits for the cluster at RAY_ADDRESS to answer (``--ray-timeout``):
#: a mistyped address fails in this time with one line instead of Ray's retries (minutes).
DEFAULT_RAY_TIMEOUT_S = 20.0
#: The scheme of a Ray client address (``ray://host:10001``).
RAY_CLIENT_SCHEME = "ray://"


def default_workers(threads: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, threads))


def plan(grid, out: str | os.PathLike, retry_failed: bool = False) -> list:
    """(run, state, what) for every run: what a sweep would do with it now (writes nothing)."""
    out = Path(out).absolute()
    entries = Manifest(out).read().get("runs", {}) if out.is_dir() else {}
    return [(r, *current(out, r, entries.get(r.name, {}), retry_failed)[::2]) for r in grid.runs]


# --- executors -----------------------------------------------------------------------------------
def _worker_env(threads: int) -> dict:
    env = dict(os.environ, **thread_environment(threads))
    root = str(Path(__file__).resolve().parents[2])          # the refgs this process runs
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env


def _last_line(path: Path) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return one_line(lines[-1]) if lines else ""


class Workers:
    """The worker processes of a local sweep; ``stop()`` terminates the running ones (SIGTERM:
    they checkpoint and stop) and starts no more."""

    def __init__(self):
        self.live, self.stopped, self.lock = set(), False, threading.Lock()

    def run(self, cmd: list, **popen) -> int | None:
        """The exit status of ``cmd``; None when stopped before it started."""
        with self.lock:
            if self.stopped:
                return None
            proc = subprocess.Popen(cmd, **popen)
            self.live.add(proc)
        try:
            return proc.wait()
        finally:
            with self.lock:
                self.live.discard(proc)

    def stop(self) -> None:
        with self.lock:
            self.stopped = True
            for proc in self.live:
                proc.terminate()


def _launch(grid, out: Path, run, env: dict, workers: Workers) -> dict:
    """Run one worker process to its end; the run's outcome."""
    log = log_path(out, run.name)
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "refgs", "run-one", str(grid.path), "--out", str(out),
           "--name", run.name, "--quiet", "--parent-pid", str(os.getpid())]
    with open(log, "ab") as fh:
        status = workers.run(cmd, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                             env=env)
    if status is None:
        return {"name": run.name, "index": run.index, "state": "pending", "error": None}
    return _settle(out, run, _death(status, log))


def _settle(out: Path, run, died: str | None = None) -> dict:
    """The outcome of a run whose worker has ended, from the manifest.  ``died``: why the worker
    ended abnormally; a run it left unfinished (neither done nor failed) is then marked failed."""
    manifest = Manifest(out)
    entry = manifest.read()["runs"].get(run.name, {})
    if died is not None and entry.get("state") not in ("done", "failed"):
        entry = manifest.set_run(run.name, state="failed", error=one_line(died),
                                 refused=False)["runs"][run.name]
    return {"name": run.name, "index": run.index, **entry}


def _death(status: int, log: Path) -> str | None:
    """Why a worker process with exit status ``status`` ended abnormally (None: it did not)."""
    if status in (0, EXIT_INTERRUPTED):
        return None
    why = f"killed by signal {-status}" if status < 0 else f"exited with status {status}"
    last = _last_line(log)
    return f"worker {why}" + (f": {last}" if last else "")


def run_local(grid, out: Path, todo: list, workers: int, threads: int):
    """Yield each run's outcome as it finishes (None every POLL_S seconds in between)."""
    env, procs = _worker_env(threads), Workers()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="refgs-sweep") as pool:
        futures = {pool.submit(_launch, grid, out, run, env, procs) for run in todo}
        try:
            while futures:
                finished, futures = wait(futures, timeout=POLL_S, return_when=FIRST_COMPLETED)
                for f in finished:
                    yield f.result()
                if not finished:
                    yield None
        finally:                      # stopped early (Ctrl-C): the runs checkpoint and stop
            if futures:
                procs.stop()


def ray_task(grid_path: str, out: str, name: str) -> dict:
    """A Ray task: one run, its output appended to its log (refgs.sweep.execute)."""
    grid = load_grid(grid_path)
    log = log_path(Path(out), name)
    log.parent.mkdir(parents=True, exist_ok=True)
    run = grid.find(name=name)
    with open(log, "a") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        try:
            return execute_run(grid, out, run)
        except runs.Interrupted:                 # stopped by SIGTERM: pending, resumable
            return {"name": name, "index": run.index, "state": "pending", "error": None}


def ray_endpoint(address: str) -> tuple[str, int] | None:
    """(host, port) of a RAY_ADDRESS that names one (``host:port``, ``ray://host:port``); None
    for the words Ray resolves itself (``auto``, ``local``)."""
    host, sep, port = address.strip().removeprefix(RAY_CLIENT_SCHEME).rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]") or "127.0.0.1", int(port)


def check_ray(timeout: float = DEFAULT_RAY_TIMEOUT_S):
    """The ray module, once ray imports and the cluster at RAY_ADDRESS (when set) accepts a
    connection within ``timeout`` seconds; ConfigError of one line naming the address
    otherwise."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--executor ray: ray is not installed (pip install 'refgs[ray]')"
                          ) from None
    if timeout <= 0:
        raise ConfigError(f"--ray-timeout: expected a positive number of seconds, got {timeout:g}")
    address = os.environ.get("RAY_ADDRESS")
    endpoint = ray_endpoint(address) if address else None
    if endpoint is not None:
        try:
            socket.create_connection(endpoint, timeout=timeout).close()
        except OSError as exc:
            why = (f"no answer within {timeout:g} s" if isinstance(exc, TimeoutError)
                   else (exc.strerror or str(exc)).lower())
            raise ConfigError(f"--executor ray: no Ray cluster answers at RAY_ADDRESS={address} "
                              f"({why}; check the address, or wait longer with --ray-timeout S)"
                              ) from None
    return ray


def _init_ray(ray, address: str | None, num_cpus: int | None, timeout: float) -> None:
    """ray.init: a local Ray started for the sweep, or the cluster at ``address`` given up after
    ``timeout`` seconds with a ConfigError naming it (a port that accepts connections but is no
    Ray cluster: Ray itself retries for minutes).  The connection is made in a thread that can
    be left behind, so Ray warns that it sets no SIGTERM handler of its own."""
    if not address:
        ray.init(address="local", num_cpus=num_cpus, include_dashboard=False,
                 log_to_driver=False, logging_level="WARNING")
        return
    failed = []

    def init():
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False,
                     logging_level="WARNING")
        except Exception as exc:                       # reported below, in the caller's thread
            failed.append(exc)

    t = threading.Thread(target=init, name="refgs-ray-init", daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive() or failed:
        why = (f"no answer within {timeout:g} s; --ray-timeout S to wait longer" if t.is_alive()
               else one_line(f"{type(failed[0]).__name__}: {failed[0]}"))
        raise ConfigError(f"--executor ray: cannot connect to RAY_ADDRESS={address} ({why})")


def run_ray(grid, out: Path, todo: list, workers: int, threads: int,
            timeout: float = DEFAULT_RAY_TIMEOUT_S):
    """Yield each run's outcome as it finishes (None every POLL_S seconds in between)."""
    ray = check_ray(timeout)
    address = os.environ.get("RAY_ADDRESS")
    started = not ray.is_initialized()
    if started:
        _init_ray(ray, address, workers * threads, timeout)
    task = ray.remote(ray_task).options(
        num_cpus=threads, max_retries=RAY_MAX_RETRIES, retry_exceptions=False,
        runtime_env={"env_vars": thread_environment(threads)})
    refs = {task.remote(str(grid.path), str(out), run.name): run for run in todo}
    try:
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1, timeout=POLL_S)
            if not ready:
                yield None
            for ref in ready:
                run = refs.pop(ref)
                try:
                    ray.get(ref)
                    died = None
                except ray.exceptions.RayError as exc:      # a lost worker, retries spent
                    cause = getattr(exc, "cause", None) or exc
                    text = str(cause).strip().splitlines()
                    died = f"{type(cause).__name__}: {text[0] if text else ''}"
                yield _settle(out, run, died)
    finally:
        for ref in refs:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


# --- the sweep -----------------------------------------------------------------------------------
def _line(outcome: dict, k: int, n: int) -> str:
    m = outcome.get("metrics") or {}
    head = f"[{k}/{n}] {outcome['state']:<7} {outcome['name']}"
    if outcome["state"] == "done":
        psnr = f"  PSNR {m['psnr']:.2f} dB" if m.get("psnr") is not None else ""
        return (f"{head}  {outcome.get('wall_s') or 0:.0f} s{psnr}  ({outcome.get('host')}"
                + (", resumed)" if outcome.get("resumed") else ")"))
    if outcome["state"] == "pending":
        return f"{head}  interrupted; resumes from its checkpoint"
    return f"{head}  {outcome.get('error')}"


def sweep(grid, out: str | os.PathLike, executor: str = "local", workers: int | None = None,
          threads: int = DEFAULT_THREADS, retry_failed: bool = False,
          progress: bool = True, ray_timeout: float = DEFAULT_RAY_TIMEOUT_S) -> dict:
    """Run every run of ``grid`` that is not done into ``out``; the final manifest.
    ``ray_timeout``: seconds the ray executor waits for the cluster at RAY_ADDRESS."""
    from tqdm import tqdm

    if executor not in EXECUTORS:
        raise ConfigError(f"--executor: expected one of {', '.join(EXECUTORS)}, got {executor!r}")
    if threads < 1 or (workers is not None and workers < 1):
        raise ConfigError("--workers / --threads-per-run: expected positive integers")
    if executor == "ray":
        check_ray(ray_timeout)              # a wrong RAY_ADDRESS: one line, before any output
    workers = workers or default_workers(threads)
    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(out)
    data = manifest.refresh(grid, retry_failed)
    todo = [r for r in grid.runs if data["runs"][r.name]["state"] in ("pending", "running")]
    c = counts(data)
    print(f"sweep {out}: {len(grid.runs)} runs, {c['done']} done, {len(todo)} to run, "
          f"{c['failed']} failed; executor {executor} on {host()}"
          + (f", {workers} workers x {threads} threads" if executor == "local" else
             f", {threads} CPUs a run"), flush=True)
    run = run_local if executor == "local" else (
        lambda *a: run_ray(*a, timeout=ray_timeout))
    bar = tqdm(total=len(todo), unit="run", desc="sweep", file=sys.stderr, dynamic_ncols=True,
               disable=None if progress and todo else True)      # None: only on a terminal
    finished = 0
    try:
        for outcome in run(grid, out, todo, workers, threads):
            c = counts(manifest.read())
            bar.set_postfix_str(f"done {c['done']}/{len(grid.runs)}, running {c['running']}, "
                                f"failed {c['failed']}", refresh=outcome is None)
            if outcome is not None:
                finished += 1
                bar.write(_line(outcome, finished, len(todo)), file=sys.stdout)
                bar.update(1)
    finally:
        bar.close()
    return manifest.read()


def report(data: dict, out: Path, grid_path: Path) -> list[str]:
    """The closing lines: the counts, and every run that is not done with its error."""
    c = counts(data)
    unfinished = c["pending"] + c["running"]
    lines = [f"{c['done']} of {len(data['runs'])} runs done"
             + (f", {c['failed']} failed" if c["failed"] else "")
             + (f", {unfinished} not finished" if unfinished else "")]
    for name, e in data["runs"].items():
        if e["state"] == "failed":
            lines.append(f"  failed   {name}: {e.get('error')}  (log: {log_path(out, name)})")
        elif e["state"] != "done":
            lines.append(f"  {e['state']:<8} {name}")
    if c["failed"]:
        lines.append(f"try the failed runs again with: refgs sweep {grid_path} --out {out} "
                     "--retry-failed")
    return lines


__all__ = ["sweep", "plan", "report", "run_local", "run_ray", "ray_task", "default_workers",
           "check_ray", "ray_endpoint", "EXECUTORS", "DEFAULT_THREADS", "RAY_MAX_RETRIES",
           "DEFAULT_RAY_TIMEOUT_S"]
