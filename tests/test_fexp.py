"""refgs.fast.fexp: the vectorisable exp of the compositing kernels is within 1 ulp of exp."""
import numpy as np
import pytest

pytest.importorskip("numba")
from refgs.fast.fexp import X_MIN, X_MIN_F32, fast_exp, fast_exp_array  # noqa: E402


def _ulps(got, dtype, x):
    exact = np.exp(x.astype(np.longdouble))
    spacing = np.spacing(exact.astype(dtype)).astype(np.longdouble)
    return np.abs(got.astype(np.longdouble) - exact) / spacing


@pytest.mark.parametrize("dtype,lo", [(np.float64, X_MIN), (np.float32, X_MIN_F32)])
def test_within_one_ulp_on_the_domain(dtype, lo):
    rng = np.random.default_rng(0)
    # the kernels' range (power in about [-6, 0] inside the screen) densely, the whole domain too
    x = np.concatenate([rng.uniform(-8.0, 0.0, 500_000), rng.uniform(lo, 0.0, 500_000),
                        -np.logspace(-30, 0, 1000), [0.0, -0.0, lo]]).astype(dtype)
    got = np.empty_like(x)
    fast_exp_array(x, got)
    assert got.dtype == dtype
    # exact within 1 ulp (+ the rounding of the exact value itself to dtype: half an ulp)
    assert _ulps(got, dtype, x).max() <= 1.5
    # and never further than 1 ulp plus numpy's own error from numpy's exp
    ref = np.exp(x)
    assert (np.abs(got - ref) <= 4 * np.spacing(ref)).all()


@pytest.mark.parametrize("dtype,lo", [(np.float64, X_MIN), (np.float32, X_MIN_F32)])
def test_clamped_domain_and_nan(dtype, lo):
    x = np.array([1.0, 50.0, lo - 1.0, -1e30, -np.inf, np.nan], dtype)
    got = np.empty_like(x)
    fast_exp_array(x, got)
    floor = np.exp(np.asarray(lo, dtype))
    assert got[0] == 1.0 and got[1] == 1.0              # x > 0 -> exp(0) (the kernels skip x > 0)
    assert np.allclose(got[2:5], floor, rtol=4 * np.finfo(dtype).eps, atol=0)
    # below X_MIN: a tiny value, so o * G < 1/255 for any opacity <= 1 (the kernels' decision)
    assert got[2:5].max() < 1e-37
    assert np.isnan(got[5])


def test_python_fallback_matches():
    x = np.linspace(-10, 0, 101)
    got = np.empty_like(x)
    fast_exp_array(x, got)
    assert np.allclose(fast_exp(x), got, rtol=4e-16, atol=0)
