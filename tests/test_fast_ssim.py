"""refgs.fast.ssim: the loss's SSIM and gradient, compiled, against the reference (MET-02, MET-04,
TRN-08) -- same value and gradient to rounding, any thread count, and used by the fast backend."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from refgs.fast.ssim import ssim_and_grad as fast_ssim  # noqa: E402
from refgs.metrics.ssim import ssim_and_grad as ref_ssim  # noqa: E402


@pytest.mark.parametrize("shape", [(37, 53, 3), (11, 11, 3), (6, 4, 3), (12, 30), (40, 9, 1), (1, 1, 3)])
def test_matches_reference(shape):
    rng = np.random.default_rng(len(shape) * 100 + shape[0])
    a = rng.uniform(0, 1, shape)
    b = np.clip(a + rng.normal(0, 0.2, shape), 0, 1)
    s0, g0 = ref_ssim(a, b)
    s1, g1 = fast_ssim(a, b)
    assert g1.shape == g0.shape and g1.dtype == g0.dtype
    assert abs(s1 - s0) <= 1e-14
    np.testing.assert_allclose(g1, g0, rtol=0, atol=1e-13 * np.abs(g0).max())


def test_float32_input_keeps_dtype_and_errors_match():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 1, (16, 20, 3)).astype(np.float32)
    b = rng.uniform(0, 1, (16, 20, 3)).astype(np.float32)
    assert fast_ssim(a, b)[1].dtype == np.float32
    with pytest.raises(ValueError, match="same shape"):
        fast_ssim(a, b[:-1])
    with pytest.raises(ValueError, match="finite"):
        fast_ssim(np.full((8, 8), np.nan), np.zeros((8, 8)))


def test_thread_count_does_not_change_the_result():
    import numba
    rng = np.random.default_rng(4)
    a, b = rng.uniform(0, 1, (45, 31, 3)), rng.uniform(0, 1, (45, 31, 3))
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        s1, g1 = fast_ssim(a, b)
        numba.set_num_threads(max(1, numba.config.NUMBA_NUM_THREADS))
        s2, g2 = fast_ssim(a, b)
    finally:
        numba.set_num_threads(old)
    assert s1 == s2 and np.array_equal(g1, g2)


def test_fast_backend_offers_it_to_the_loss():
    from refgs.backends import get_backend
    from refgs.train.loss import photometric_loss
    be = get_backend("fast")
    rng = np.random.default_rng(5)
    a, b = rng.uniform(0, 1, (20, 24, 3)), rng.uniform(0, 1, (20, 24, 3))
    l0, g0 = photometric_loss(a, b)
    l1, g1 = photometric_loss(a, b, ssim_fn=be.ssim_and_grad)
    assert abs(l0 - l1) <= 1e-14 and np.allclose(g0, g1, rtol=0, atol=1e-14)
    assert not hasattr(get_backend("reference"), "ssim_and_grad")
