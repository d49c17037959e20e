"""The backend runs in a worker process; the oracle survives whatever it does (ORC-11).

    info = open_backend("my_backend:backend", memory_limit_mib=8192)   # BackendError: exit 2
    info.session.begin_check(timeout=300)      # the backend's time budget for one check
    out = info.obj.render(gaussians, camera, config)   # a call into the worker
    info.session.close()

:class:`Session` starts ``python -m oracle.worker`` (oracle/worker.py) as a subprocess speaking
over a socket pair (frames of oracle/wire.py: JSON and ``.npz`` arrays, never pickle), so the
oracle's own process never imports the backend's module.  One worker serves check after check;
it is replaced only when it dies or is killed.  :class:`RemoteBackend` is the backend as the
evaluators see it (``render``, ``render_backward``, ``stage_*``): an exception the backend raises
is re-raised here with its type name and the line it came from; a worker that dies, runs out of
memory or outlives the check's time budget raises :class:`WorkerLost` (a BaseException, so that
neither the evaluators nor hypothesis take it for an ordinary failure), which the runner turns
into the check's status ``crash`` or ``timeout``.

The time budget counts the backend's time only (from sending a request to its answer, summed
over the check), so a slow oracle never times a backend out.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path

from .protocol import BackendError, BackendInfo, Malformed
from .wire import decode, encode

#: seconds of backend time one check may use (``--timeout``; 0 = no limit)
DEFAULT_TIMEOUT = 300.0
#: MiB of data memory the worker may use (``--memory-limit``; 0 = no limit); a backend with
#: numba or torch loaded uses 0.3-0.5 GiB (measured: VmData of a worker rendering 64x48 images)
DEFAULT_MEMORY_LIMIT_MIB = 8192
#: seconds a worker may take to import and describe the backend (numba and torch take seconds)
START_TIMEOUT = 300.0
#: how often a waiting call looks whether the worker is still alive (seconds)
POLL_S = 0.2
#: seconds a worker told to stop gets before it is killed
STOP_GRACE_S = 2.0
#: fault-handler frames quoted in a crash message
CRASH_FRAMES = 2


class WorkerLost(BaseException):
    """The worker died (``kind`` "crash") or was killed at the time limit ("timeout")."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind, self.reason = kind, reason


class RemoteError(Exception):
    """An exception the backend raised in the worker: ``type_name``, ``where`` (file:line)."""

    def __init__(self, type_name: str, message: str, where: str):
        super().__init__(message)
        self.type_name, self.where = type_name, where


class OutputReleased(RuntimeError):
    """render_backward named a render output the worker no longer holds (it keeps the last
    ``worker.KEEP_OUTPUTS``): render the scene again for a fresh one."""


class RemoteValueError(RemoteError, ValueError):
    """The backend raised a ValueError (or a subclass): invalid input rejected (API-03)."""


def _fault_frames(path: Path) -> str:
    """``Fatal Python error: ...`` and the innermost frames of the fault handler's log."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    head = next((ln.strip() for ln in lines if ln.startswith("Fatal Python error")), "")
    frames = [ln.strip() for ln in lines if ln.strip().startswith("File ")]
    frames = [f for f in frames if "oracle/worker.py" not in f][:CRASH_FRAMES]
    if not head and not frames:
        return ""
    return "; ".join(filter(None, [head] + [f.replace('File "', "").replace('", line ', ":") for f in frames]))


def death_reason(returncode: int | None, fault_log: Path | None = None) -> str:
    """Why a worker died, in words: the signal or the exit status, and the frame it was in."""
    if returncode is None:
        what = "the worker stopped answering"
    elif returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        what = f"the worker was killed by {name}"
        if name == "SIGKILL":
            what += " (the system kills a process that exhausts the machine's memory)"
    else:
        what = f"the worker exited with status {returncode}"
    frames = _fault_frames(fault_log) if fault_log is not None else ""
    return what + (f" ({frames})" if frames else "")


class Session:
    """One backend served by a worker process, restarted on demand (module docstring)."""

    def __init__(self, spec: str, memory_limit_mib: int | None = DEFAULT_MEMORY_LIMIT_MIB,
                 start_timeout: float | None = START_TIMEOUT):
        self.spec = spec
        self.memory_limit_mib = memory_limit_mib or 0
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen | None = None
        self.conn: Connection | None = None
        self.budget: float | None = None
        self.timeout: float | None = None
        self.starts = 0
        self.description: dict | None = None
        self._dir = Path(tempfile.mkdtemp(prefix="oracle-worker-"))

    @property
    def fault_log(self) -> Path:
        return self._dir / f"fault-{self.starts}.log"

    # ---- life cycle ----------------------------------------------------------------------------
    def start(self) -> dict:
        """Start a worker and wait for the backend's description; BackendError (one line) if the
        backend cannot be loaded."""
        self._stop()
        self.starts += 1
        parent, child = socket.socketpair()
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
        cmd = [sys.executable, "-m", "oracle.worker", "--fd", str(child.fileno()), "--spec", self.spec,
               "--memory-limit-mib", str(self.memory_limit_mib), "--fault-log", str(self.fault_log),
               "--sys-path", json.dumps([p for p in sys.path if p])]
        try:
            self.proc = subprocess.Popen(cmd, pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL,
                                         env=env, start_new_session=True)
        finally:
            child.close()
        self.conn = Connection(parent.detach())
        try:
            reply = self._receive(self.start_timeout, "loading the backend")
        except WorkerLost as lost:
            why = (f"the backend did not load within {self.start_timeout:g} s; the worker was killed"
                   if lost.kind == "timeout" else lost.reason)
            raise BackendError(f"--backend {self.spec}: {why}") from None
        if "load_error" in reply:
            self._stop()
            raise BackendError(reply["load_error"])
        self.description = reply["ready"]
        return self.description

    def begin_check(self, timeout: float | None) -> None:
        """Give the next check ``timeout`` seconds of backend time (None or 0: no limit)."""
        self.timeout = float(timeout) if timeout else None
        self.budget = self.timeout

    def close(self) -> None:
        """Stop the worker and remove its temporary folder."""
        self._stop()
        shutil.rmtree(self._dir, ignore_errors=True)

    def _stop(self) -> None:
        proc, conn = self.proc, self.conn
        self.proc = self.conn = None
        if conn is not None:
            try:
                conn.send_bytes(encode({"op": "exit"}))
            except OSError:
                pass
        if proc is not None:
            try:
                proc.wait(STOP_GRACE_S if conn is not None else 0.01)
            except subprocess.TimeoutExpired:
                self._kill(proc)
        if conn is not None:
            conn.close()

    @staticmethod
    def _kill(proc: subprocess.Popen) -> None:
        """Kill the worker and anything it started (its own process group)."""
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        proc.wait()

    # ---- calls ---------------------------------------------------------------------------------
    def call(self, op: str, what: str, **payload) -> dict:
        """Send one request and return the answer; WorkerLost if the worker dies or the check's
        budget runs out while it works; ``what`` names the call in messages."""
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        try:
            self.conn.send_bytes(encode({"op": op, **payload}))
        except OSError:
            raise self._lost("crash", what) from None
        t0 = time.monotonic()
        try:
            reply = self._receive(self.budget, what)
        finally:
            if self.budget is not None:
                self.budget = max(0.0, self.budget - (time.monotonic() - t0))
        if "fatal" in reply:
            proc = self.proc
            try:
                proc.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                self._kill(proc)
            self._stop()
            raise WorkerLost("crash", f"{reply['fatal']}" + (
                f" (the worker's memory limit is {self.memory_limit_mib} MiB)"
                if "MemoryError" in reply["fatal"] and self.memory_limit_mib else ""))
        if "oracle_error" in reply:
            raise RuntimeError(f"oracle worker: {reply['oracle_error']}")
        return reply

    def _receive(self, limit: float | None, what: str) -> dict:
        t0 = time.monotonic()
        while True:
            left = None if limit is None else limit - (time.monotonic() - t0)
            wait = POLL_S if left is None else max(0.0, min(POLL_S, left))
            try:
                if self.conn.poll(wait):
                    return decode(self.conn.recv_bytes())
            except (EOFError, OSError):
                raise self._lost("crash", what) from None
            if self.proc.poll() is not None and not self.conn.poll(0):
                raise self._lost("crash", what)
            if left is not None and left <= 0:
                raise self._lost("timeout", what)

    def _lost(self, kind: str, what: str) -> WorkerLost:
        proc = self.proc
        if kind == "timeout":
            self._kill(proc)
            limit = self.timeout if self.timeout is not None else self.start_timeout
            reason = (f"{what} did not return within the time limit ({limit:g} s of backend time "
                      f"per check); the worker was killed")
        else:
            try:
                proc.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                self._kill(proc)
            reason = f"{death_reason(proc.returncode, self.fault_log)} during {what}"
        if self.conn is not None:
            self.conn.close()
        self.proc = self.conn = None
        return WorkerLost(kind, reason)


class RemoteOutput(dict):
    """A render result held by the worker: its fields (arrays or :class:`Malformed`) and
    ``handle``, by which render_backward names it."""

    handle: int = -1


def _fields(reply: dict) -> dict:
    out = dict(reply.get("fields", {}))
    out.update({k: Malformed(v) for k, v in reply.get("malformed", {}).items()})
    return out


def _raise_remote(reply: dict) -> None:
    r = reply.get("raised")
    if r is not None:
        cls = RemoteValueError if r["value_error"] else RemoteError
        raise cls(r["type"], r["message"], r["where"])


class RemoteBackend:
    """The backend of a :class:`Session`, with the methods of the protocol (ORC-01)."""

    def __init__(self, session: Session):
        self.session = session

    def render(self, gaussians, camera, config):
        reply = self.session.call("render", "render", args=[gaussians, camera, config])
        _raise_remote(reply)
        out = RemoteOutput(_fields(reply))
        out.handle = reply["handle"]
        return out

    def render_backward(self, out, v_image, v_alpha=None, v_depth=None):
        cot = {"v_image": v_image}
        cot.update({k: v for k, v in (("v_alpha", v_alpha), ("v_depth", v_depth)) if v is not None})
        reply = self.session.call("render_backward", "render_backward", handle=out.handle,
                                  cotangents=cot)
        if "released" in reply:
            raise OutputReleased(f"render output {out.handle} is no longer held by the worker")
        _raise_remote(reply)
        return _fields(reply)

    def _stage(self, name, args, fields):
        reply = self.session.call("stage", f"stage_{name}", name=name, args=list(args), fields=fields)
        _raise_remote(reply)
        if "array" in reply:
            return reply["array"]
        if "malformed_value" in reply:
            return Malformed(reply["malformed_value"])
        return _fields(reply)

    def stage_covariance(self, quats, log_scales):
        return self._stage("covariance", (quats, log_scales), None)

    def stage_projection(self, means, cov3d, opacities, camera, config):
        return self._stage("projection", (means, cov3d, opacities, camera, config),
                           ["means2d", "conics", "depths", "radii", "cov2d", "visible"])

    def stage_sh(self, means, sh, campos, degree):
        return self._stage("sh", (means, sh, campos, int(degree)), None)

    def stage_composite(self, means2d, conics, opacities, colors, depths, radii, camera, config):
        return self._stage("composite", (means2d, conics, opacities, colors, depths, radii, camera, config),
                           ["image", "alpha", "depth", "n_contrib"])


def open_backend(spec: str, memory_limit_mib: int | None = DEFAULT_MEMORY_LIMIT_MIB,
                 start_timeout: float | None = START_TIMEOUT) -> BackendInfo:
    """Start a worker for ``spec`` and return the backend as the oracle sees it (its
    ``session`` must be closed); BackendError (one line) if it cannot be loaded."""
    session = Session(spec, memory_limit_mib, start_timeout)
    try:
        desc = session.start()
    except BaseException:
        session.close()
        raise
    return BackendInfo.from_description(desc, RemoteBackend(session), session)
