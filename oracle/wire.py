"""The messages between the oracle and its backend worker: JSON plus numpy arrays, no pickle.

A message is a JSON-able value (dicts, lists, strings, numbers, None) in which numpy arrays and
refgs' containers may appear; :func:`encode` turns it into bytes, :func:`decode` back:

    frame = 8-byte little-endian length of the JSON header | JSON header | the arrays' bytes

Arrays are replaced in the header by ``{"__array__": [dtype, shape, offset]}`` (the dtype as its
numpy string, e.g. ``"<f4"``) and travel as their raw C-order bytes after the header, read back
with ``np.frombuffer`` (no zip, no pickle: a few microseconds per array); ``refgs.Gaussians``,
``refgs.Camera`` and ``refgs.RenderConfig`` travel as tagged dicts of their fields.  Only numeric and boolean arrays can be encoded: an
object array (what ``np.asarray`` makes of something that is not an array) raises
:class:`NotNumeric`, and the worker reports it as a malformed output instead.  Decoding never
imports anything: the oracle's process never unpickles, and so never imports, what a backend
returns (docs/spec/oracle.md ORC-11).
"""
from __future__ import annotations

import json
import struct

import numpy as np

import refgs

#: array kinds that travel: bool, signed and unsigned integers, floats, complex
NUMERIC_KINDS = "biufc"
_LEN = struct.Struct("<Q")


class NotNumeric(TypeError):
    """An array whose dtype is not numeric or boolean cannot be sent (the message says which)."""


def _config_fields(cfg: refgs.RenderConfig) -> dict:
    return {"profile": str(cfg.profile), "sh_degree": cfg.sh_degree,
            "background": [float(v) for v in cfg.background], "antialiased": bool(cfg.antialiased),
            "opacity_scale": None if cfg.opacity_scale is None else np.asarray(cfg.opacity_scale)}


def _pack(value, arrays: dict):
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in NUMERIC_KINDS:
            raise NotNumeric(f"an array of dtype {value.dtype} cannot be sent (numeric arrays only)")
        data = np.ascontiguousarray(value).tobytes()
        offset = sum(len(b) for b in arrays)
        arrays.append(data)
        return {"__array__": [value.dtype.str, list(value.shape), offset]}
    if isinstance(value, np.generic):
        return _pack(value.item(), arrays) if value.dtype.kind in NUMERIC_KINDS + "U" else _pack(
            np.asarray(value), arrays)
    if isinstance(value, refgs.Gaussians):
        return {"__gaussians__": {f: _pack(np.asarray(getattr(value, f)), arrays)
                                  for f in refgs.Gaussians.FIELDS}}
    if isinstance(value, refgs.Camera):
        return {"__camera__": {"world_to_camera": _pack(np.asarray(value.world_to_camera), arrays),
                               "K": _pack(np.asarray(value.K), arrays),
                               "width": int(value.width), "height": int(value.height)}}
    if isinstance(value, refgs.RenderConfig):
        return {"__config__": _pack(_config_fields(value), arrays)}
    if isinstance(value, dict):
        return {str(k): _pack(v, arrays) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_pack(v, arrays) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise NotNumeric(f"a value of type {type(value).__name__} cannot be sent")


def _array(spec, payload: bytes) -> np.ndarray:
    dtype, shape, offset = spec
    dt = np.dtype(str(dtype))
    if dt.kind not in NUMERIC_KINDS or dt.hasobject:
        raise ValueError(f"oracle wire: dtype {dtype!r} is not a numeric dtype")
    count = int(np.prod(shape, dtype=np.int64))
    flat = np.frombuffer(payload, dtype=dt, count=count, offset=int(offset))
    return flat.reshape([int(n) for n in shape]).copy()


def _unpack(value, arrays):
    if isinstance(value, dict):
        if "__array__" in value:
            return _array(value["__array__"], arrays)
        if "__gaussians__" in value:
            d = value["__gaussians__"]
            return refgs.Gaussians(*(_unpack(d[f], arrays) for f in refgs.Gaussians.FIELDS))
        if "__camera__" in value:
            d = value["__camera__"]
            return refgs.Camera(_unpack(d["world_to_camera"], arrays), _unpack(d["K"], arrays),
                                int(d["width"]), int(d["height"]))
        if "__config__" in value:
            d = _unpack(value["__config__"], arrays)
            return refgs.RenderConfig(profile=d["profile"], sh_degree=d["sh_degree"],
                                      background=tuple(d["background"]),
                                      antialiased=d["antialiased"], opacity_scale=d["opacity_scale"])
        return {k: _unpack(v, arrays) for k, v in value.items()}
    if isinstance(value, list):
        return [_unpack(v, arrays) for v in value]
    return value


def encode(message) -> bytes:
    """``message`` as one frame (see the module docstring); NotNumeric if it holds a value that
    cannot travel."""
    arrays: list = []
    header = json.dumps(_pack(message, arrays)).encode("utf-8")
    return b"".join([_LEN.pack(len(header)), header, *arrays])


def decode(frame: bytes):
    """The message of one frame (ValueError if the frame is not one)."""
    if len(frame) < _LEN.size:
        raise ValueError("oracle wire: truncated frame")
    (n,) = _LEN.unpack_from(frame)
    header = json.loads(frame[_LEN.size:_LEN.size + n].decode("utf-8"))
    return _unpack(header, memoryview(frame)[_LEN.size + n:])
