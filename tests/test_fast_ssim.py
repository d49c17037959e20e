"""refgs.fast.ssim: the loss's SSIM and gradient, compiled, against the reference (MET-02, MET-04,
TRN-08) -- same value and gradient to rounding, any thread count, and used by the fast backend;
and the whole loss (MET-08), whose gradient is the spec's bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from refgs.fast.ssim import l1_ssim_loss  # noqa: E402
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


# heights across the bands of the fused pass (LOSS_BAND_ROWS = 64): one band, a band edge at
# 64 (and 10 rows on either side of it), a last band of 3 rows, fewer rows than a tap window
@pytest.mark.parametrize("shape", [(37, 53, 3), (12, 30), (6, 4, 3), (1, 1, 3), (64, 9, 3),
                                   (74, 6), (131, 17, 3), (200, 5, 2)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("form", ["l1_plus", "blend"])
def test_whole_loss_gradient_is_the_specs_bit_for_bit(shape, dtype, form):
    """l1_ssim_loss computes the spec's gradient expression element for element (one rounding to
    the render's dtype at the end), so training with it gives the same bytes; its loss value sums
    the L1 by rows instead of numpy's pairwise mean (last bits). Ties render == gt (sign 0) and
    both signs occur."""
    from refgs.train.loss import photometric_loss
    rng = np.random.default_rng(shape[0] * 7 + len(shape))
    gt = rng.uniform(0, 1, shape).astype(np.float32)
    render = np.clip(gt + rng.normal(0, 0.2, shape), 0, 1).astype(dtype)
    render.flat[::5] = gt.flat[::5]                       # d = 0: the subgradient 0
    l0, g0 = photometric_loss(render, gt, 0.2, form, fast_ssim)
    l1, g1 = photometric_loss(render, gt, 0.2, form, fast_ssim, l1_ssim_loss)
    assert g1.dtype == g0.dtype == dtype and g1.shape == g0.shape
    assert np.array_equal(g1, g0)
    assert abs(l1 - l0) <= 1e-14
    l2, g2 = photometric_loss(render, gt, 0.2, form)   # the numpy spec path
    np.testing.assert_allclose(g1, g2, rtol=0, atol=1e-13 * np.abs(g2).max())
    assert abs(l1 - l2) <= 1e-13


def test_whole_loss_errors_and_threads():
    import numba
    with pytest.raises(ValueError, match="finite"):
        l1_ssim_loss(np.full((8, 8, 3), np.inf, np.float32), np.zeros((8, 8, 3), np.float32), 1, .2)
    with pytest.raises(ValueError, match="same shape"):
        l1_ssim_loss(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)), 1.0, 0.2)
    rng = np.random.default_rng(6)
    a, b = rng.uniform(0, 1, (45, 31, 3)), rng.uniform(0, 1, (45, 31, 3))
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        r1 = l1_ssim_loss(a, b, 1.0, 0.2)
        numba.set_num_threads(max(1, numba.config.NUMBA_NUM_THREADS))
        r2 = l1_ssim_loss(a, b, 1.0, 0.2)
    finally:
        numba.set_num_threads(old)
    assert r1[0] == r2[0] and np.array_equal(r1[1], r2[1])
