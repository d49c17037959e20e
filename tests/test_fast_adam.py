"""refgs.fast.adam: Adam's update compiled, bit-identical to the numpy spec (TRN-02, issue 7)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from refgs.fast.adam import adam_update  # noqa: E402
from refgs.train.adam import Adam  # noqa: E402
from refgs.train.schedule import sh_lr  # noqa: E402


def _state(rng, dtype, n=257, k=16):
    p = {"means": rng.standard_normal((n, 3)), "sh": rng.standard_normal((n, k, 3)),
         "opacity_logits": rng.standard_normal(n), "quats": rng.standard_normal((n, 4))}
    return {name: a.astype(dtype) for name, a in p.items()}


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_fused_adam_is_bit_identical_to_numpy(dtype):
    """Thirty steps with gradients over eight decades, a (1, K, 1) learning rate, a skipped
    parameter, rows frozen per row and SH frozen per (row, coefficient): every parameter and
    moment equal bit for bit, and the kernel took every update (no silent fallback)."""
    rng = np.random.default_rng(7)
    p_ref = _state(rng, dtype)
    p_fast = {k: v.copy() for k, v in p_ref.items()}
    ref, fast = Adam(p_ref), Adam(p_fast)
    taken = []

    def kernel(*args):
        ok = adam_update(*args)
        taken.append(ok)
        return ok

    fast.kernel = kernel
    n = len(p_ref["means"])
    lrs = {"means": 1.6e-4, "sh": sh_lr(16), "opacity_logits": 0.05, "quats": 1e-3}
    for step in range(30):
        g = {k: (rng.standard_normal(v.shape) * 10.0 ** rng.integers(-6, 3)).astype(dtype)
             for k, v in p_ref.items()}
        g["means"][rng.random(n) < 0.1] = 0            # rows without gradient
        frozen = None
        if step % 3 == 1:
            rows = rng.random(n) < 0.4
            sh_keep = np.zeros((n, 16, 1), bool)
            sh_keep[rows, 1:] = True
            frozen = {"quats": rows, "sh": sh_keep}
        skip = {"opacity_logits"} if step in (5, 11) else set()
        ref.step(p_ref, g, lrs, skip=skip, frozen_rows=frozen)
        fast.step(p_fast, g, lrs, skip=skip, frozen_rows=frozen)
    assert taken and all(taken)
    for name in p_ref:
        for a, b in ((p_ref[name], p_fast[name]), (ref.m[name], fast.m[name]),
                     (ref.v[name], fast.v[name])):
            assert a.dtype == b.dtype == dtype
            assert np.array_equal(a, b), name
    assert ref.steps == fast.steps


def test_fused_adam_declines_shapes_it_does_not_take():
    """A learning rate varying by row, or a non-contiguous gradient: False and nothing changed."""
    rng = np.random.default_rng(1)
    p = rng.standard_normal((6, 3))
    m, v = np.zeros_like(p), np.zeros_like(p)
    before = p.copy()
    g = rng.standard_normal((6, 3))
    assert not adam_update(p, g, m, v, np.full((6, 1), 0.1), None, 1, (0.9, 0.999), 1e-15)
    assert not adam_update(p, rng.standard_normal((6, 6))[:, ::2], m, v, 0.1, None, 1,
                           (0.9, 0.999), 1e-15)
    assert np.array_equal(p, before) and not m.any() and not v.any()


def test_fast_backend_trainer_uses_the_kernel():
    from refgs.backends import get_backend
    b = get_backend("fast")
    p = {"x": np.ones((4, 3))}
    from refgs.train.trainer import Trainer  # noqa: F401  (the trainer passes backend.adam_update)
    calls = []
    a = Adam(p, kernel=lambda *args: calls.append(1) or b.adam_update(*args))
    a.step(p, {"x": np.ones((4, 3))}, {"x": 0.1})
    assert calls == [1] and np.allclose(p["x"], 0.9)
    assert not hasattr(get_backend("reference"), "adam_update")
