"""Photometric loss (MET-08) value and gradient; PSNR (MET-01)."""
import numpy as np
import pytest

from refgs.metrics import psnr, ssim
from refgs.train.loss import FORM_BLEND, FORM_L1_PLUS, LAMBDA_DSSIM, l1_and_grad, photometric_loss


def _away_from_kink(shape, seed, margin=0.05):
    """render, gt with |render - gt| >= margin everywhere (FD steps never cross the L1 kink)."""
    rng = np.random.default_rng(seed)
    gt = rng.random(shape)
    step = rng.uniform(margin, 0.3, shape) * rng.choice([-1.0, 1.0], shape)
    return gt + step, gt


def test_defaults_are_dropgaussian():
    assert LAMBDA_DSSIM == 0.2
    r, g = _away_from_kink((12, 13, 3), seed=0)
    assert photometric_loss(r, g)[0] == photometric_loss(r, g, 0.2, "l1_plus")[0]


@pytest.mark.parametrize("form,lam", [(FORM_L1_PLUS, 0.2), (FORM_BLEND, 0.2), (FORM_L1_PLUS, 0.7), (FORM_BLEND, 1.0)])
def test_loss_value(form, lam):
    r, g = _away_from_kink((15, 11, 3), seed=1)
    l1 = np.mean(np.abs(r - g))
    s = ssim(r, g)
    expected = (l1 if form == FORM_L1_PLUS else (1 - lam) * l1) + lam * (1 - s)
    loss, _ = photometric_loss(r, g, lam, form)
    assert abs(loss - expected) <= 1e-15


@pytest.mark.parametrize("form", [FORM_L1_PLUS, FORM_BLEND])
@pytest.mark.parametrize("shape,seed", [((12, 14, 3), 2), ((7, 9, 1), 3)])
def test_loss_grad_matches_finite_differences(form, shape, seed):
    """MET-08: d loss / d render vs central differences on every entry, float64."""
    r, g = _away_from_kink(shape, seed)
    _, grad = photometric_loss(r, g, 0.2, form)
    h = 1e-6
    fd = np.zeros_like(r)
    for idx in np.ndindex(r.shape):
        rp, rm = r.copy(), r.copy()
        rp[idx] += h
        rm[idx] -= h
        fd[idx] = (photometric_loss(rp, g, 0.2, form)[0] - photometric_loss(rm, g, 0.2, form)[0]) / (2 * h)
    rel = np.max(np.abs(grad - fd)) / np.max(np.abs(fd))
    assert rel <= 1e-6, rel


def test_l1_subgradient_at_zero_is_zero():
    """MET-08: entries with render == gt get no L1 gradient; identical images: loss 0, grad 0."""
    r, g = _away_from_kink((10, 12, 3), seed=4)
    loss, grad = photometric_loss(g.copy(), g)
    assert loss == pytest.approx(0.0, abs=1e-15) and np.max(np.abs(grad)) <= 1e-13
    r[2, 3, 1] = g[2, 3, 1]
    _, g_l1 = l1_and_grad(r, g)
    assert g_l1[2, 3, 1] == 0.0
    assert np.all(np.abs(np.delete(g_l1.ravel(), np.ravel_multi_index((2, 3, 1), r.shape))) == 1 / r.size)


def test_float32_render_gives_float32_grad():
    r, g = _away_from_kink((9, 9, 3), seed=5)
    loss64, grad64 = photometric_loss(r, g)
    loss32, grad32 = photometric_loss(r.astype(np.float32), g.astype(np.float32))
    assert grad32.dtype == np.float32 and grad64.dtype == np.float64
    assert abs(loss32 - loss64) < 1e-6


@pytest.mark.parametrize("kwargs,match", [({"form": "mse"}, "form must be"),
                                          ({"lambda_dssim": 1.5}, "lambda_dssim"),
                                          ({"lambda_dssim": float("nan")}, "lambda_dssim")])
def test_loss_bad_arguments(kwargs, match):
    r, g = _away_from_kink((9, 9, 3), seed=6)
    with pytest.raises(ValueError, match=match):
        photometric_loss(r, g, **kwargs)
    with pytest.raises(ValueError, match="same shape"):
        photometric_loss(r, g[:, :8])


# --- PSNR (MET-01) ---------------------------------------------------------------------------------
def test_psnr_known_value_and_skimage():
    from skimage.metrics import peak_signal_noise_ratio

    assert psnr(np.zeros((4, 5, 3)), np.full((4, 5, 3), 0.1)) == pytest.approx(20.0, abs=1e-12)
    rng = np.random.default_rng(7)
    a, b = rng.random((16, 20, 3)), rng.random((16, 20, 3))
    assert abs(psnr(a, b) - peak_signal_noise_ratio(b, a, data_range=1.0)) <= 1e-12


def test_psnr_identical_is_inf_and_errors():
    a = np.random.default_rng(8).random((6, 6, 3))
    assert psnr(a, a.copy()) == float("inf")
    with pytest.raises(ValueError, match="same shape"):
        psnr(a, a[:5])
    b = a.copy()
    b[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="finite"):
        psnr(a, b)
