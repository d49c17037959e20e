"""Hostile backends: renderers that hang, crash, run out of memory or return malformed output (ORC-11).

Each is refgs (float32, inria profile) with one way of misbehaving; the oracle must run to the
end on every one of them, give each check its verdict and name the cause
(tests/test_oracle_isolation.py):

    hangs_on_third_call      render sleeps forever from its third call on      -> timeout
    segfaults                render reads address 0 (ctypes.string_at(0)) on its second call
                                                                               -> crash (SIGSEGV)
    returns_float16          image and alpha in float16                        -> error (dtype)
    channel_first            image as (3, H, W)                                -> error (shape)
    nan_pixel                one NaN in the image, at the last pixel's green channel
                                                                               -> error (NaN, pixel)
    raises_runtime_error     render raises RuntimeError on valid input         -> error (exception)
    allocates_without_bound  render allocates 64 MiB blocks until memory runs out
                                                                               -> crash (MemoryError)

The call counters are per process: a fresh worker starts counting again.  The allocating
backend refuses to run without a memory limit on its process (the oracle's worker sets one),
so that importing it by mistake cannot take a machine's memory.
"""
from __future__ import annotations

import ctypes
import time

import numpy as np

import refgs

#: seconds the hanging backend sleeps per step (it never returns)
HANG_STEP_S = 1.0
#: bytes the allocating backend takes per step
ALLOC_STEP = 64 << 20
#: the allocating backend refuses to run with a larger (or no) data-memory limit than this
ALLOC_GUARD = 64 << 30


class _Hostile:
    """refgs at float32, inria profile, forward only (ORC-01); subclasses misbehave in render."""

    profile = "inria"
    dtype = "float32"
    version = refgs.__version__

    def __init__(self, name: str, cause: str):
        self.name, self.cause = name, cause
        self.calls = 0

    def reference(self, gaussians, camera, config) -> refgs.RenderOutput:
        return refgs.render(gaussians.astype(self.dtype), camera, config)


class HangsOnThirdCall(_Hostile):
    def render(self, gaussians, camera, config):
        self.calls += 1
        while self.calls >= 3:
            time.sleep(HANG_STEP_S)
        return self.reference(gaussians, camera, config)


class Segfaults(_Hostile):
    def render(self, gaussians, camera, config):
        self.calls += 1
        if self.calls >= 2:
            ctypes.string_at(0)                  # reads address 0: SIGSEGV
        return self.reference(gaussians, camera, config)


class ReturnsFloat16(_Hostile):
    def render(self, gaussians, camera, config):
        out = self.reference(gaussians, camera, config)
        return {"image": out.image.astype(np.float16), "alpha": out.alpha.astype(np.float16)}


class ChannelFirst(_Hostile):
    def render(self, gaussians, camera, config):
        out = self.reference(gaussians, camera, config)
        return {"image": np.ascontiguousarray(np.moveaxis(out.image, -1, 0)), "alpha": out.alpha}


class NanPixel(_Hostile):
    def render(self, gaussians, camera, config):
        out = self.reference(gaussians, camera, config)
        image = out.image.copy()
        image[-1, -1, 1] = np.nan
        return {"image": image, "alpha": out.alpha}


class RaisesRuntimeError(_Hostile):
    def render(self, gaussians, camera, config):
        raise RuntimeError("planted: this backend fails on every input")


class AllocatesWithoutBound(_Hostile):
    def render(self, gaussians, camera, config):
        import resource
        soft = resource.getrlimit(resource.RLIMIT_DATA)[0]
        if soft == resource.RLIM_INFINITY or soft > ALLOC_GUARD:
            raise RuntimeError("allocates_without_bound runs only under a data-memory limit of at "
                               f"most {ALLOC_GUARD >> 30} GiB (the oracle's worker sets one)")
        blocks = []
        while True:
            blocks.append(np.ones(ALLOC_STEP // 8))       # touched: really allocated


hangs_on_third_call = HangsOnThirdCall("hostile-hangs-on-third-call", "timeout")
segfaults = Segfaults("hostile-segfaults", "crash")
returns_float16 = ReturnsFloat16("hostile-returns-float16", "error")
channel_first = ChannelFirst("hostile-channel-first", "error")
nan_pixel = NanPixel("hostile-nan-pixel", "error")
raises_runtime_error = RaisesRuntimeError("hostile-raises-runtime-error", "error")
allocates_without_bound = AllocatesWithoutBound("hostile-allocates-without-bound", "crash")

#: name -> (backend, the status its render-level checks get, a phrase the message must contain)
HOSTILE = {
    "hangs_on_third_call": (hangs_on_third_call, "timeout", "time limit"),
    "segfaults": (segfaults, "crash", "SIGSEGV"),
    "returns_float16": (returns_float16, "error", "dtype=float16"),
    "channel_first": (channel_first, "error", "image.shape=(3,"),
    "nan_pixel": (nan_pixel, "error", "=nan, but should be finite"),
    "raises_runtime_error": (raises_runtime_error, "error", "RuntimeError: planted"),
    "allocates_without_bound": (allocates_without_bound, "crash", "MemoryError"),
}
