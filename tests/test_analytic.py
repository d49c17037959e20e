"""One isotropic Gaussian straight ahead, against closed forms (PRJ-04, RAS-04, RAS-06, CNV-08).

An isotropic Gaussian of world standard deviation s at depth z on the optical axis of a camera with
focal f has the dilated screen covariance sigma^2 I with sigma^2 = (f s / z)^2 + eps2d (PRJ-03,
PRJ-04; eps2d = 0.3 in both profiles).  Its alpha is o exp(-r^2 / (2 sigma^2)), cut to 0 below 1/255
(RAS-04), i.e. beyond the Mahalanobis radius R = sqrt(2 ln(255 o)).  Hence, in the continuum,

    peak alpha       = o                                  (for o below the cap)
    integral of alpha = 2 pi sigma^2 (o - 1/255)          (the 1/255 cut removes 2 pi sigma^2 / 255)
    centre of mass    = the projected mean (fx x / z + cx, fy y / z + cy) (CNV-08)

The image is a lattice sum at pixel centres.  For the smooth part the lattice sum equals the
integral up to terms of order exp(-2 pi^2 sigma^2) (Poisson summation: negligible for sigma >= 1.5)
and a midpoint-rule boundary term of size ~ pi R^2 / (12 * 255) < 0.01.  The cut at 1/255 is a jump
of height 1/255 along an ellipse; only pixels whose square the ellipse crosses (centre within
sqrt(2)/2 px of it) can be off, each by at most 1/255.  That count, computed in the test from the
geometry alone, is the tolerance (``_cut_tolerance``); it is a few percent of the integral and well
below the effect of the dilation (0.3 / sigma^2 = 4 .. 12 % for the sizes used).  The opacities are
chosen with R < 3, so the inria radius 3 sqrt(lambda) covers every fragment above 1/255 and tile
truncation (RAS-01) plays no part; one Gaussian never reaches the transmittance stop.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from refgs import Camera, Gaussians, RenderConfig, render

W, H = 48, 32
F = 40.0
Z = 2.5
EPS2D = 0.3
#: Small enough that R = sqrt(2 ln(255 o)) < 3 (no tile truncation in the inria profile).
OPACITIES = (0.3, 0.15)
#: Projected standard deviations f s / z in pixels (before dilation).
SIZES_PX = (1.5, 2.5, 3.5)
#: Midpoint-rule boundary term bound (module docstring).
MIDPOINT_SLACK = 0.01


def _scene(size_px, opacity, cx, cy, x, y, profile):
    K = np.array([[F, 0, cx], [0, F, cy], [0, 0, 1.0]])
    cam = Camera(np.eye(4), K, W, H)
    s = size_px * Z / F
    g = Gaussians([[x, y, Z]], [[math.log(s)] * 3], [[0.3, -0.5, 0.2, 0.7]],
                  [math.log(opacity / (1 - opacity))], np.zeros((1, 1, 3)))
    return render(g, cam, RenderConfig(profile=profile))


def _cut_tolerance(u, v, sigma2, opacity):
    """Pixels whose square the alpha = 1/255 circle crosses, times the jump 1/255."""
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    r = np.hypot(jj - u, ii - v)
    R = math.sqrt(2 * math.log(255 * opacity)) * math.sqrt(sigma2)
    return np.count_nonzero(np.abs(r - R) <= math.sqrt(0.5)) / 255, R


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("size_px", SIZES_PX)
@pytest.mark.parametrize("opacity", OPACITIES)
def test_isotropic_gaussian_closed_forms(profile, size_px, opacity):
    """Peak alpha, alpha integral 2 pi sigma^2 (o - 1/255), centre of mass (RAS-04, PRJ-04, CNV-08)."""
    sigma2 = size_px ** 2 + EPS2D
    # on the optical axis (the Jacobian is then f / z I) with the principal point on a pixel
    # centre: (u, v) = (cx, cy) = (24.5, 16.5)
    out = _scene(size_px, opacity, W / 2 + 0.5, H / 2 + 0.5, 0.0, 0.0, profile)
    u, v = out.means2d[0]
    assert (u, v) == (24.5, 16.5)
    assert out.cov2d[0] == pytest.approx([sigma2, 0.0, sigma2], rel=1e-13, abs=1e-13)
    assert out.alpha.max() == pytest.approx(opacity, rel=1e-14)
    assert out.alpha[16, 24] == out.alpha.max()
    total = out.alpha.sum()
    expected = 2 * math.pi * sigma2 * (opacity - 1 / 255)
    tol, R = _cut_tolerance(u, v, sigma2, opacity)
    assert R + 1 < min(v, H - v), "the Gaussian must fit in the image"
    assert abs(total - expected) <= tol + MIDPOINT_SLACK, (total, expected, tol)
    # the check resolves the dilation: for the smallest size (0.3 / sigma^2 = 12 %) the integral
    # without it is off by more than the tolerance
    if size_px == min(SIZES_PX):
        assert abs(total - 2 * math.pi * size_px ** 2 * (opacity - 1 / 255)) > tol + MIDPOINT_SLACK
    # centre of mass: exactly the sampled centre (the lattice is symmetric about it)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    assert np.sum(out.alpha * jj) / total == pytest.approx(u, abs=1e-12)
    assert np.sum(out.alpha * ii) / total == pytest.approx(v, abs=1e-12)


@pytest.mark.parametrize("profile", ["inria", "gsplat"])
@pytest.mark.parametrize("cx,cy", [(20.3, 13.7), (27.1, 18.4), (24.0, 16.0)])
def test_isotropic_gaussian_centre_of_mass_off_centre(profile, cx, cy):
    """Off-centre principal points: the alpha-weighted centre of mass is (fx x / z + cx,
    fy y / z + cy) (CNV-08) within the cut tolerance (each of the crossing pixels moves the first
    moment by at most (R + 1) / 255)."""
    size_px, opacity = 2.5, 0.3
    x = y = 0.0                                  # straight ahead: u = cx, v = cy
    sigma2 = size_px ** 2 + EPS2D
    out = _scene(size_px, opacity, cx, cy, x, y, profile)
    u, v = F * x / Z + cx, F * y / Z + cy
    assert out.means2d[0] == pytest.approx([u, v], abs=1e-13)
    total = out.alpha.sum()
    tol, R = _cut_tolerance(u, v, sigma2, opacity)
    expected = 2 * math.pi * sigma2 * (opacity - 1 / 255)
    assert abs(total - expected) <= tol + MIDPOINT_SLACK
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    com_tol = tol * (R + 1) / (expected - tol)
    assert com_tol < 0.25, "the bound must resolve a half-pixel convention error"
    assert abs(np.sum(out.alpha * jj) / total - u) <= com_tol
    assert abs(np.sum(out.alpha * ii) / total - v) <= com_tol
    # the original's integer-centre rule (u' = u - 0.5 sampled at integers) is the same image;
    # a renderer sampling at integer coordinates with u itself would shift the centre by 0.5
    assert abs(np.sum(out.alpha * (jj - 0.5)) / total - u) > 0.5 - com_tol
