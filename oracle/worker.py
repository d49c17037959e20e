"""The backend worker: a child process that loads one backend and answers the oracle's calls (ORC-11).

    python -m oracle.worker --fd FD --spec module:object [--memory-limit-mib M] [--fault-log PATH]
                            [--sys-path JSON]

Started by oracle/isolation.py, never by hand.  It dies with the oracle's process, limits its
own memory (``RLIMIT_DATA``, so that a backend allocating without bound gets a MemoryError
instead of the machine's memory) and core dumps, writes Python's fault handler output to ``--fault-log`` (the frame a segfault
happened in), loads the backend with :func:`oracle.protocol.load_backend`, and then serves
requests on the socket ``FD`` (frames of oracle/wire.py) until it is told to stop or the oracle
goes away:

    {"op": "render", "args": [gaussians, camera, config]}
        -> {"handle": h, "fields": {name: array}, "malformed": {name: why}}
    {"op": "render_backward", "handle": h, "cotangents": {"v_image": ..., ...}}
        -> {"fields": {...}, "malformed": {...}}, or {"released": h} when the worker no longer
           holds that output (it keeps the last KEEP_OUTPUTS)
    {"op": "stage", "name": "projection", "args": [...], "fields": [names] | None}
        -> {"fields": ..., "malformed": ...} or {"array": a} / {"malformed_value": why}

An exception raised by the backend comes back as ``{"raised": {"type", "value_error", "message",
"where"}}``; a MemoryError, SystemExit or other fatal condition as ``{"fatal": why}``, after which
the worker exits.  Outputs travel as they are (no conversion to the declared dtype): the oracle
judges what the backend returned.
"""
from __future__ import annotations

import argparse
import faulthandler
import json
import os
import sys
import traceback

#: render outputs kept for render_backward (the oracle asks for the gradient of the last one)
KEEP_OUTPUTS = 8
#: exit status of a worker that stopped after a fatal condition (MemoryError, SystemExit)
FATAL_EXIT = 3
#: bytes per MiB
MIB = 1 << 20
#: prctl option: the signal this process gets when its parent dies (linux/prctl.h)
PR_SET_PDEATHSIG = 1


def limit_resources(memory_limit_mib: int | None) -> None:
    """No core files; at most ``memory_limit_mib`` MiB of data (heap and private mappings:
    RLIMIT_DATA, which unlike RLIMIT_AS does not count address space a GPU runtime reserves)."""
    try:
        import resource
    except ImportError:                      # not POSIX: no limits
        return
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if memory_limit_mib:
        lim = int(memory_limit_mib) * MIB
        hard = resource.getrlimit(resource.RLIMIT_DATA)[1]
        if hard != resource.RLIM_INFINITY:
            lim = min(lim, hard)
        resource.setrlimit(resource.RLIMIT_DATA, (lim, hard))


def die_with_parent() -> None:
    """Ask Linux to kill this worker when the oracle's process ends (PR_SET_PDEATHSIG), so that
    a backend stuck in a loop does not outlive an oracle that was killed; elsewhere a no-op (the
    worker still stops at end of input when the oracle goes away)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _where(exc: BaseException) -> str:
    """``file:line in function`` of the backend's frame that raised ``exc`` (the first frame
    outside this module) and, when the exception came from deeper, of the innermost frame."""
    tb = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename != __file__]
    if not tb:
        return ""
    first, last = tb[0], tb[-1]
    out = f"{first.filename}:{first.lineno} in {first.name}"
    return out if last is first else f"{out} -> {last.filename}:{last.lineno} in {last.name}"


def _read(obj, name: str, label: str):
    """``(array, None)``, ``(None, why it is malformed)``, or ``(None, None)`` when absent."""
    from .protocol import get_field
    from .wire import NUMERIC_KINDS
    try:
        val = get_field(obj, name)
    except Exception as exc:                               # an unreadable field is malformed
        return None, f"{label} could not be read as an array: {type(exc).__name__}: {exc}"
    if val is None:
        return None, None
    if val.dtype.kind not in NUMERIC_KINDS:
        return None, (f"{label} is not a numeric array (numpy made dtype {val.dtype} of a "
                      f"{type(_raw(obj, name)).__name__})")
    return val, None


def _fields(obj, names) -> tuple[dict, dict]:
    """The named fields of a backend's result as arrays, and why any could not be read."""
    got, bad = {}, {}
    for name in names:
        val, why = _read(obj, name, name)
        if why is not None:
            bad[name] = why
        elif val is not None:
            got[name] = val
    return got, bad


def _raw(obj, name):
    return obj.get(name) if isinstance(obj, dict) else getattr(obj, name, None)


class Server:
    """Answers requests for one loaded backend (``info``: a protocol.BackendInfo)."""

    def __init__(self, info):
        self.info = info
        self.outputs: dict[int, object] = {}
        self.next_handle = 0

    def handle(self, req: dict) -> dict:
        from .protocol import GAUSSIAN_OUTPUTS, GRAD_FIELDS, PIXEL_OUTPUTS
        obj, op = self.info.obj, req.get("op")
        try:
            if op == "render":
                out = obj.render(*req["args"])
                h = self.next_handle
                self.next_handle += 1
                self.outputs[h] = out
                for old in [k for k in self.outputs if k <= h - KEEP_OUTPUTS]:
                    del self.outputs[old]
                got, bad = _fields(out, PIXEL_OUTPUTS + GAUSSIAN_OUTPUTS)
                return {"handle": h, "fields": got, "malformed": bad}
            if op == "render_backward":
                if req["handle"] not in self.outputs:
                    return {"released": req["handle"]}
                grads = obj.render_backward(self.outputs[req["handle"]], **req["cotangents"])
                got, bad = _fields(grads, GRAD_FIELDS + ("means2d",))
                return {"fields": got, "malformed": bad}
            if op == "stage":
                res = self.info.stages[req["name"]](*req["args"])
                if req.get("fields") is not None:
                    got, bad = _fields(res, req["fields"])
                    return {"fields": got, "malformed": bad}
                val, why = _read({"value": res}, "value", f"the result of stage_{req['name']}")
                if val is not None:
                    return {"array": val}
                return {"malformed_value": why or f"stage_{req['name']} returned None"}
            return {"oracle_error": f"unknown request {op!r}"}
        except MemoryError as exc:
            return {"fatal": f"the backend raised MemoryError in {op} at {_where(exc)}"}
        except Exception as exc:
            return {"raised": {"type": type(exc).__name__, "value_error": isinstance(exc, ValueError),
                               "message": str(exc)[:2000], "where": _where(exc)}}
        except BaseException as exc:               # SystemExit and the like: the worker stops
            if isinstance(exc, KeyboardInterrupt):
                raise
            return {"fatal": f"the backend raised {type(exc).__name__}({exc}) in {op} at {_where(exc)}"}


def serve(conn, spec: str) -> None:
    """Load ``spec`` and answer requests on ``conn`` until EOF or {"op": "exit"}."""
    from .protocol import BackendError, load_backend
    from .wire import NotNumeric, decode, encode

    def send(msg):
        conn.send_bytes(encode(msg))

    try:
        info = load_backend(spec)
    except BackendError as exc:
        send({"load_error": str(exc)})
        return
    except BaseException as exc:                    # the backend's module raised on import
        if isinstance(exc, KeyboardInterrupt):
            raise
        send({"load_error": f"--backend {spec}: loading the backend raised {type(exc).__name__}: "
                            f"{exc} ({_where(exc)})"})
        return
    send({"ready": info.description()})
    server = Server(info)
    while True:
        try:
            req = decode(conn.recv_bytes())
        except (EOFError, OSError):
            return
        if req.get("op") == "exit":
            return
        reply = server.handle(req)
        try:
            send(reply)
        except NotNumeric as exc:                   # cannot happen for _fields' output; be explicit
            send({"oracle_error": f"reply could not be encoded: {exc}"})
        if "fatal" in reply:
            os._exit(FATAL_EXIT)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m oracle.worker")
    p.add_argument("--fd", type=int, required=True)
    p.add_argument("--spec", required=True)
    p.add_argument("--memory-limit-mib", type=int, default=0)
    p.add_argument("--fault-log", default=None)
    p.add_argument("--sys-path", default=None)
    a = p.parse_args(argv)
    die_with_parent()
    limit_resources(a.memory_limit_mib)
    if a.fault_log:
        log = open(a.fault_log, "w")              # kept open for the life of the process
        faulthandler.enable(file=log, all_threads=False)
    os.dup2(2, 1)                 # a backend's prints go to stderr, never into the oracle's output
    sys.stdout = sys.stderr
    if a.sys_path:
        extra = [p for p in json.loads(a.sys_path) if p not in sys.path]
        sys.path[:0] = extra
    from multiprocessing.connection import Connection
    conn = Connection(a.fd)
    try:
        serve(conn, a.spec)
    finally:
        conn.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
