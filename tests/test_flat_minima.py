"""Property tests of the paper's method primitives (clauses FM-01..FM-05, DG-01).

Statistical tests state their false-alarm rate: the probability that the test fails for a
correct implementation and a fresh random seed.  Seeds are fixed here, so each run is
deterministic; the rate says how unlucky a seed would have to be.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import erfc

import refgs
from refgs.covariance import covariance_3d
from strategies import max_examples
from refgs.methods import (CLAMP_MODES, NoiseShape, clamp_displacement, clipped_fraction,
                           drop_opacity_scale, drop_rate, magnitude_schedule, perturb_probability,
                           sap_offsets)

#: z-score bound of the Gaussian tail tests: two-sided P(|Z| > 5) = 5.7e-7 per statistic
Z_BOUND = 5.0


def copies(n, log_scales, quat, dtype=np.float64):
    """N identical Gaussians (so one sap_offsets call gives N iid samples of delta)."""
    return refgs.Gaussians(np.zeros((n, 3)), np.tile(log_scales, (n, 1)), np.tile(quat, (n, 1)),
                           np.zeros(n), np.zeros((n, 1, 3))).astype(dtype)


gaussian_shape = st.tuples(
    st.lists(st.floats(-3, 1), min_size=3, max_size=3),                 # anisotropic log-scales
    st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))


@settings(max_examples=max_examples(8), deadline=None)
@given(shape=gaussian_shape, seed=st.integers(0, 2 ** 31), alpha=st.sampled_from([1.0, 0.5, 0.25]))
def test_fm01_covariance_is_alpha2_gamma2_sigma(shape, seed, alpha):
    """FM-01, FM-03: with p = 1 and no clamp, delta ~ N(0, alpha^2 gamma^2 Sigma).

    Whitened samples w = (alpha gamma L)^-1 delta (Sigma = L L^T) must have identity covariance:
    each of the 6 distinct entries of the sample covariance of M samples has standard deviation
    sqrt(1/M) (off-diagonal) or sqrt(2/M) (diagonal); all within Z_BOUND standard deviations.
    False-alarm rate <= 6 x 5.7e-7 = 3.4e-6; the mean is tested too (3 x 5.7e-7)."""
    log_s, q = shape
    m = 40_000
    g = copies(m, log_s, q)
    off, mask = sap_offsets(g, gamma=2.0, p=1.0, alpha=alpha, clamp=False, rng=np.random.default_rng(seed))
    assert mask.all()
    sigma = covariance_3d(g.quats[:1], g.log_scales[:1])["cov3d"][0]
    L = np.linalg.cholesky(sigma)
    w = np.linalg.solve(alpha * 2.0 * L, off.T).T
    assert np.all(np.abs(w.mean(0)) <= Z_BOUND / np.sqrt(m))
    c = w.T @ w / m
    sd = np.where(np.eye(3, dtype=bool), np.sqrt(2 / m), np.sqrt(1 / m))
    assert np.all(np.abs(c - np.eye(3)) <= Z_BOUND * sd), c


@settings(max_examples=max_examples(10), deadline=None)
@given(shape=gaussian_shape, seed=st.integers(0, 2 ** 31), alpha=st.floats(0.05, 3.0),
       mode=st.sampled_from([m for m in CLAMP_MODES if m != "none"]),
       dtype=st.sampled_from([np.float64, np.float32]))
def test_fm04_clamp_bounds_hold_for_every_sample(shape, seed, alpha, mode, dtype):
    """FM-04: every clamp reading keeps ||delta|| <= ||s||_2 for every sample, plus its own bound,
    up to the one rounding of the offsets to the Gaussians' dtype (the clamp itself is exact in
    float64): 1e-12 relative in float64, 4 eps = 4.8e-7 in float32."""
    log_s, q = shape
    g = copies(2000, log_s, q, dtype)
    off, _ = sap_offsets(g, p=1.0, alpha=alpha, clamp=mode, rng=np.random.default_rng(seed))
    assert off.dtype == dtype
    off = off.astype(np.float64)
    s = np.exp(np.asarray(g.log_scales[0], np.float64))
    R = covariance_3d(g.quats[:1].astype(np.float64), g.log_scales[:1].astype(np.float64))["R"][0]
    local = off @ R                                   # R^T delta, row-wise
    rel = 1e-12 if dtype == np.float64 else 4 * float(np.finfo(np.float32).eps)
    tol = rel * np.linalg.norm(s)
    assert np.all(np.linalg.norm(off, axis=-1) <= np.linalg.norm(s) + tol)
    if mode == "axis":
        assert np.all(np.abs(local) <= s + tol)
    elif mode == "box":
        assert np.all(np.max(np.abs(local) / s, axis=-1) <= 1 + rel * np.max(np.linalg.norm(s) / s))
    elif mode == "ellipsoid":
        assert np.all(np.linalg.norm(local / s, axis=-1) <= 1 + rel * np.max(np.linalg.norm(s) / s))


def test_fm04_axis_clipped_fraction_matches_erfc():
    """FM-04: per axis the clamp binds with probability erfc(1/(sqrt 2 alpha gamma)) (62 % at
    alpha = 1, gamma = 2).  Monte-Carlo with n = 200k x 3 axes: standard error < 1e-3;
    bound 5e-3 (> 5 sigma, false-alarm rate < 6e-7)."""
    for alpha in (0.25, 0.5, 1.0):
        expected = erfc(1 / (np.sqrt(2) * alpha * 2.0))
        assert abs(clipped_fraction(alpha, "axis") - expected) < 5e-3
    assert abs(erfc(1 / (np.sqrt(2) * 2.0)) - 0.617) < 1e-3


def test_fm02_mask_frequency_is_binomial_and_offsets_zero_off_mask():
    """FM-02: mask ~ Bernoulli(p): |k - n p| <= 5 sqrt(n p (1-p)) (false-alarm rate 5.7e-7);
    offsets exactly zero where the mask is False, and non-zero where it is True."""
    n, p = 100_000, 0.3
    g = copies(n, [-1.0, -2.0, -0.5], [1.0, 0.2, -0.3, 0.1])
    off, mask = sap_offsets(g, p=p, rng=np.random.default_rng(7))
    k = int(mask.sum())
    assert abs(k - n * p) <= Z_BOUND * np.sqrt(n * p * (1 - p))
    assert np.all(off[~mask] == 0.0)
    assert np.all(np.any(off[mask] != 0.0, axis=-1))


def test_fm02_same_seed_same_offsets_and_dtype():
    """FM-02: masks and offsets come from the explicitly passed Generator only; dtype kept."""
    for dt in (np.float32, np.float64):
        g = copies(500, [-1.0, -2.0, -0.5], [1.0, 0.2, -0.3, 0.1], dt)
        a = sap_offsets(g, rng=np.random.default_rng(3))
        b = sap_offsets(g, rng=np.random.default_rng(3))
        assert a[0].dtype == dt and a[1].dtype == bool
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_sap_offsets_validation_switch():
    """validate=False (the trainer's hook, whose render checks theta_hat) skips only the input
    check: the same offsets and mask; by default a bad field is named."""
    g = copies(300, [-1.0, -2.0, -0.5], [1.0, 0.2, -0.3, 0.1], np.float32)
    a = sap_offsets(g, rng=np.random.default_rng(5))
    b = sap_offsets(g, rng=np.random.default_rng(5), validate=False)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    means = g.means.copy()
    means[7, 1] = np.nan
    with pytest.raises(ValueError, match="Gaussians.means"):
        sap_offsets(g.replace(means=means), rng=np.random.default_rng(5))


def test_fm01_offsets_of_the_perturbed_rows_are_the_whole_array_formula():
    """FM-01/FM-02: sap_offsets works on the perturbed rows only; each row equals, bit for bit,
    the whole-array formula delta = R clamp(alpha gamma sigma z) applied to every row and then
    masked (the draws are made for every row, in the documented order, either way)."""
    from refgs.covariance import normalize_quats, quat_to_rotmat
    rng = np.random.default_rng(11)
    n = 3000
    g = refgs.Gaussians(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) - 2,
                        rng.normal(size=(n, 4)), rng.normal(size=n), rng.normal(size=(n, 4, 3)))
    for noise in (NoiseShape(), NoiseShape("iso_max"), NoiseShape("iso_fixed", 0.05)):
        for clamp in ("axis", "ellipsoid", "none"):
            off, mask = sap_offsets(g, gamma=2.0, p=0.3, alpha=0.6, clamp=clamp,
                                    rng=np.random.default_rng(5), noise=noise)
            draw = np.random.default_rng(5)
            assert np.array_equal(mask, draw.random(n) < 0.3)
            z = draw.standard_normal((n, 3))
            R = quat_to_rotmat(normalize_quats(g.quats)[0])
            s = np.exp(g.log_scales)
            sigma = {"anisotropic": s, "iso_max": np.repeat(s.max(-1, keepdims=True), 3, -1),
                     "iso_fixed": np.full_like(s, 0.05)}[noise.kind]
            full = np.einsum("nij,nj->ni", R, clamp_displacement(0.6 * 2.0 * sigma * z, s, clamp))
            assert np.array_equal(off, np.where(mask[:, None], full, 0.0))


def test_fm01_validates_like_render():
    """FM-01: bad input is refused like render does (ValueError naming the field)."""
    g = copies(3, [-1.0, -2.0, -0.5], [1.0, 0.0, 0.0, 0.0])
    bad = g.replace(quats=np.zeros((3, 4)))
    with pytest.raises(ValueError, match="Gaussians.quats"):
        sap_offsets(bad, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="rng"):
        sap_offsets(g, rng=None)
    with pytest.raises(ValueError, match="clamp"):
        sap_offsets(g, clamp="sideways", rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="Gaussians.means"):
        sap_offsets(g.replace(means=np.full((3, 3), np.nan)), rng=np.random.default_rng(0))


def test_fm03_schedule_exact():
    """FM-03: alpha(t) = t/T exactly at 0, T/2, T; p constant unless ramped."""
    T = 10_000
    assert magnitude_schedule(0, T) == 0.0
    assert magnitude_schedule(T // 2, T) == 0.5
    assert magnitude_schedule(T, T) == 1.0
    assert perturb_probability(123, T) == 0.3
    assert perturb_probability(T // 2, T, ramp=True) == 0.15
    with pytest.raises(ValueError, match="--iters"):
        magnitude_schedule(1, 0)


def test_fm01_noise_shapes():
    """FM-01 (ablation): isotropic variants have covariance sigma*^2 gamma^2 I."""
    m = 40_000
    g = copies(m, np.log([0.1, 0.2, 0.6]), [0.9, 0.1, 0.3, -0.2])
    for kind, s_star in (("iso_max", 0.6), ("iso_mean", 0.3), ("iso_fixed", 0.05)):
        off, _ = sap_offsets(g, p=1.0, clamp=False, rng=np.random.default_rng(1),
                             noise=NoiseShape(kind, fixed_sigma=0.05))
        c = off.T @ off / m / (2.0 * s_star) ** 2
        sd = np.where(np.eye(3, dtype=bool), np.sqrt(2 / m), np.sqrt(1 / m))
        assert np.all(np.abs(c - np.eye(3)) <= Z_BOUND * sd), (kind, c)


def test_clamp_displacement_modes_direction():
    """FM-04: direction-preserving readings keep the direction; 'axis' clips per component."""
    s = np.array([[1.0, 2.0, 0.5]])
    local = np.array([[3.0, 1.0, 0.1]])
    assert np.allclose(clamp_displacement(local, s, "axis"), [[1.0, 1.0, 0.1]])
    for mode in ("box", "ellipsoid", "norm"):
        out = clamp_displacement(local, s, mode)
        assert np.allclose(np.cross(out, local), 0)
    inside = np.array([[0.1, 0.1, 0.1]])
    for mode in CLAMP_MODES:
        assert np.array_equal(clamp_displacement(inside, s, mode), inside)


def test_dg01_keep_rate_and_compensation():
    """DG-01: keep ~ Bernoulli(1 - r), r = 0.2 t/T (binomial 5-sigma bound, false-alarm 5.7e-7);
    kept Gaussians' opacity factor is exactly 1/(1 - r), dropped ones 0."""
    n, T = 200_000, 10_000
    for t in (0, 2500, 10_000):
        r = drop_rate(t, T)
        scale, keep = drop_opacity_scale(n, t, T, np.random.default_rng(t))
        k = int(keep.sum())
        assert abs(k - n * (1 - r)) <= Z_BOUND * np.sqrt(n * r * (1 - r)) + 1e-9
        assert np.all(scale[keep] == 1.0 / (1.0 - r)) and np.all(scale[~keep] == 0.0)
    assert drop_rate(10_000, 10_000) == pytest.approx(0.2)


def test_fm04_clipped_fraction_depends_on_the_axis_ratios_only_for_norm():
    """FM-04: axis/box/ellipsoid clamp in units of s (same Monte-Carlo draws give identical
    fractions for any scales); norm binds less for elongated Gaussians."""
    for mode in ("axis", "box", "ellipsoid"):
        assert clipped_fraction(1.0, mode, n=20_000) == clipped_fraction(1.0, mode, n=20_000,
                                                                         scales=(1.0, 0.1, 0.01))
    iso, needle = clipped_fraction(1.0, "norm", n=20_000), clipped_fraction(1.0, "norm", n=20_000,
                                                                            scales=(1.0, 0.01, 0.01))
    assert iso > needle + 0.2
